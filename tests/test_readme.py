"""The README's Python blocks run as written (in order, one namespace), so the first thing a user
copies works: the render, the stages composed by hand, and the fit."""

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parent.parent / "README.md"


def test_readme_python_blocks_run():
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    assert len(blocks) >= 3, "the README shows a render, the stages and a fit"
    ns: dict = {}
    for code in blocks:
        exec(compile(code, str(README), "exec"), ns)
    r = ns["r"]
    assert r.successful, r.result
    # the README fits its own render from the scene's values: it stays at them
    np.testing.assert_allclose(r.values, r.start, rtol=1e-4)
    assert np.all(np.isfinite(r.stderr))
