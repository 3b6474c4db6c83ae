"""The package version, written once (pyproject.toml reads the same string), and the versions of what the
numbers depend on (recorded in every optimize manifest and in every batch job's key)."""

__version__ = "0.1.0"

#: the packages whose versions can change dtoc's outputs
DEPENDENCIES = ("torch", "numpy", "scipy", "pypulseq", "pydantic")


def package_versions() -> dict[str, str | None]:
    """{python, dtoc, torch, numpy, scipy, pypulseq, pydantic: version} (None: not installed); no package is
    imported (read from the installed metadata)."""
    import importlib.metadata as md
    import platform

    out: dict[str, str | None] = {"python": platform.python_version(), "dtoc": __version__}
    for pkg in DEPENDENCIES:
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out
