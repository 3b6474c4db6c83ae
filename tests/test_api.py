"""The public façade: `import dtoc` is light, exposes its __all__, and the docs/api.md example runs."""

import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_import_dtoc_is_light_and_exports_all():
    code = (
        "import sys, dtoc\n"
        "assert 'torch' not in sys.modules and 'pypulseq' not in sys.modules, sorted(sys.modules)\n"
        "missing = [n for n in dtoc.__all__ if getattr(dtoc, n, None) is None]\n"
        "assert not missing, missing\n"
        "print(len(dtoc.__all__))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert int(r.stdout) >= 10


def test_facade_names_survive_subpackage_imports():
    """A facade name that equals a sub-package would be replaced by the module once the sub-package loads."""
    import dtoc
    import dtoc.identify.api  # noqa: F401
    import dtoc.optimize.run  # noqa: F401

    assert all(callable(getattr(dtoc, n)) for n in dtoc.__all__ if n != "__version__")


def test_docs_api_example_runs(monkeypatch, capsys):
    text = (REPO / "docs" / "api.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.S)
    assert len(blocks) == 1
    monkeypatch.chdir(REPO)
    exec(compile(blocks[0], "docs/api.md", "exec"), {"__name__": "docs_api_example"})
    out = capsys.readouterr().out
    assert "max k error before" in out and "->" in out
