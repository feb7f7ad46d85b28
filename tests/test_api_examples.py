"""The Python API's examples run as written.

Every ```python block of docs/api.md and of the README's "Python API" section runs as written,
from an empty working directory, as a user would run it after ``pip install``. The README's
example must print a finite power (W) and gradient (W/rpm). Two tiers:

- the default run checks every block statically, in under a second: it compiles, every name
  it takes from sgn_jax exists, and every call of one binds to that name's signature (the
  regression that breaks an example while the API's own tests pass: a name or parameter
  renamed or removed). Running the blocks takes minutes; the API's behaviour is what the
  API's own tests check;
- the slow tier (``pytest -m slow``) runs each block in a fresh process of its own, cold: the
  caches off (``SGN_JAX_NO_CACHE=1``, set by conftest.py and inherited by the process, and no
  JAX compilation cache), exactly as a first-time user runs it.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
API_DOC = ROOT / "docs" / "api.md"
README = ROOT / "README.md"

_BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)
_NUMBER = r"([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|nan|inf|-inf)"


def _python_blocks(text: str) -> list[str]:
    return _BLOCK.findall(text)


def _api_doc_blocks() -> list[tuple[str, str]]:
    """(section heading, code) of every python block of docs/api.md, in order."""
    blocks, heading = [], "intro"
    for part in re.split(r"^(## .*)$", API_DOC.read_text(), flags=re.MULTILINE):
        if part.startswith("## "):
            heading = part[3:].strip()
            continue
        blocks.extend((heading, code) for code in _python_blocks(part))
    return blocks


def _readme_section() -> str:
    """The README's "## Python API" section (up to the next level-2 heading)."""
    text = README.read_text()
    match = re.search(r"^## Python API\n(.*?)(?=^## |\Z)", text, re.MULTILINE | re.DOTALL)
    assert match, "README.md has no '## Python API' section"
    return match.group(1)


def _cold_env() -> dict[str, str]:
    """The environment of a first-time user: no package cache, no JAX compilation cache."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_")}
    return dict(env, SGN_JAX_NO_CACHE="1")


def _run(code: str, cwd: Path) -> subprocess.CompletedProcess:
    env = _cold_env()
    result = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True,
                            text=True, timeout=600)
    assert result.returncode == 0, (
        f"the example failed (exit {result.returncode}):\n{code}\n--- stdout ---\n"
        f"{result.stdout[-3000:]}\n--- stderr ---\n{result.stderr[-5000:]}")
    return result


API_BLOCKS = _api_doc_blocks()


def _slug(heading: str) -> str:
    return re.sub(r"[^a-z0-9]+", "_", heading.lower()).strip("_")


def test_the_api_doc_has_an_example_per_public_entry_point():
    headings = " ".join(h for h, _ in API_BLOCKS)
    import sgn_jax

    # The public API is the root's __all__, the same list as sgn_jax.api.__all__.
    for name in [n for n in sgn_jax.__all__ if n != "__version__"]:
        if name == "DesignStudy":  # documented with design_study, which returns it
            name = "design_study` and `DesignStudy"
        assert f"`{name}`" in headings, f"docs/api.md has no example section for {name}"


README_ID = "readme_python_api"


def _readme_block() -> str:
    blocks = _python_blocks(_readme_section())
    assert len(blocks) == 1, f"the README's Python API section has {len(blocks)} python blocks"
    return blocks[0]


def _assert_finite_power_and_gradient(out: str) -> None:
    power = re.search(rf"power\b.*?{_NUMBER}\s*W(?![/\w])", out, re.IGNORECASE)
    grad = re.search(rf"{_NUMBER}\s*W/rpm", out)
    assert power and grad, f"no power in W and gradient in W/rpm in:\n{out}"
    for match in (power, grad):
        assert math.isfinite(float(match.group(1))), out


# ---------------------------------------------------------------------------------------------
# Slow tier: each block in a fresh process of its own, cold.


def _param(heading: str, code: str):
    return pytest.param(code, id=_slug(heading))


@pytest.mark.slow
@pytest.mark.parametrize("code", [_param(h, c) for h, c in API_BLOCKS])
def test_api_doc_example_runs(code, tmp_path):
    result = _run(code, tmp_path)
    assert result.stdout.strip(), "the example printed nothing"


@pytest.mark.slow
def test_readme_example_prints_a_finite_power_and_gradient(tmp_path):
    _assert_finite_power_and_gradient(_run(_readme_block(), tmp_path).stdout)


# ---------------------------------------------------------------------------------------------
# Default tier: every block compiles and calls the API as it is now (no block is run).
#
# Running the blocks takes minutes (each compiles rollouts and design studies of the shipped
# hidden-256 model); what they call is tested in the default run by the API's own tests
# (tests/test_design.py runs the README's study, tests/test_api.py, tests/test_sweep.py, ...).
# What breaks an example without breaking those tests is the API moving under it: a name
# removed or renamed, a parameter renamed or dropped, one positional argument too many. That
# is checked here for every call of a public name, statically, in well under a second.

def _module_aliases(tree: ast.AST) -> tuple[dict[str, object], dict[str, object]]:
    """(alias -> module, name -> object) of the block's ``import sgn_jax...`` and
    ``from sgn_jax... import name`` statements."""
    modules, names = {}, {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("sgn_jax"):
                    target = alias.asname or alias.name.split(".")[0]
                    module = importlib.import_module(alias.name if alias.asname else "sgn_jax")
                    modules[target] = module
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("sgn_jax"):
            module = importlib.import_module(node.module)
            for alias in node.names:
                assert hasattr(module, alias.name), f"{node.module} has no {alias.name}"
                names[alias.asname or alias.name] = getattr(module, alias.name)
    return modules, names


def _api_calls(code: str) -> list[tuple[str, object, ast.Call]]:
    """(what, callable, call node) of every call of an sgn_jax name in the block."""
    tree = ast.parse(code)
    modules, names = _module_aliases(tree)
    calls = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if (isinstance(func, ast.Attribute) and isinstance(func.value, ast.Name)
                and func.value.id in modules):
            module = modules[func.value.id]
            assert hasattr(module, func.attr), (
                f"{module.__name__}.{func.attr} does not exist (renamed or removed?)")
            calls.append((f"{module.__name__}.{func.attr}", getattr(module, func.attr), node))
        elif isinstance(func, ast.Name) and func.id in names:
            calls.append((func.id, names[func.id], node))
    return calls


def _check_binds(what: str, obj: object, call: ast.Call) -> bool:
    """Whether the call's arguments bind to ``obj``'s signature (False: not checkable, a
    ``*args``/``**kwargs`` call or no signature). Raises AssertionError when they do not."""
    if any(isinstance(a, ast.Starred) for a in call.args) or any(
            k.arg is None for k in call.keywords):
        return False
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):
        return False
    try:
        signature.bind(*[None] * len(call.args), **{k.arg: None for k in call.keywords})
    except TypeError as error:
        raise AssertionError(f"{what}({ast.unparse(call)[len(ast.unparse(call.func)) + 1:]} "
                             f"no longer fits {what}{signature}: {error}") from None
    return True


ALL_BLOCKS = {README_ID: _readme_block(), **{_slug(h): c for h, c in API_BLOCKS}}


@pytest.mark.parametrize("name", sorted(ALL_BLOCKS))
def test_api_doc_example_calls_the_api_as_it_is(name):
    code = ALL_BLOCKS[name]
    compile(code, f"<example {name}>", "exec")
    for what, obj, call in _api_calls(code):
        assert callable(obj), f"{what} is not callable"
        _check_binds(what, obj, call)


def test_the_static_check_catches_a_renamed_parameter_and_a_removed_name():
    """The twin must fail on what breaks an example: here, on purpose."""
    calls = _api_calls(ALL_BLOCKS[README_ID])
    checked = [what for what, obj, call in calls if _check_binds(what, obj, call)]
    assert "sgn_jax.api.design_study" in checked and "sgn_jax.api.make_packings" in checked
    what, obj, call = next(c for c in calls if c[0] == "sgn_jax.api.design_study")
    renamed = ast.parse("sj.design_study(m, c, n, p, length=0.03)").body[0].value
    with pytest.raises(AssertionError, match="no longer fits"):
        _check_binds(what, obj, renamed)
    with pytest.raises(AssertionError, match="does not exist"):
        _api_calls("import sgn_jax.api as sj\nsj.design_studies(1)\n")
