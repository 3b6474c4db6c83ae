"""The optional compiled core of the PDG pre-pass (dtoc/sim/_pdg_split.c).  Everything else is in pyproject.toml.

The extension is optional: where no C compiler is there (or the build fails) the install goes on without it and the
pre-pass runs its numpy formulation, which builds the same graph bit for bit (tests/test_prepass_native.py)."""

import sys

from setuptools import Extension, setup

flags = [] if sys.platform == "win32" else ["-O2", "-ffp-contract=off"]
setup(
    ext_modules=[Extension("dtoc.sim._pdg_split", ["dtoc/sim/_pdg_split.c"], optional=True, extra_compile_args=flags)]
)
