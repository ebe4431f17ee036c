"""The package's layout: no import cycle between its modules, no module over about 600
lines without a reason stated at its top, and importing it changes no JAX setting."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "safewbc_jax"
MAX_LINES = 650   # "about 600"; a longer module says why in a line starting "Size:"


def _module_name(path: Path) -> str:
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(path: Path, modules: set) -> set:
    """Package modules that ``path`` imports anywhere (at module level, or lazily inside a
    function: two modules that import each other are a cycle either way), resolved to
    modules of the package."""
    tree = ast.parse(path.read_text())
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        for n in names:
            if n in modules and n != me:
                out.add(n)
    return out


def test_no_import_cycle():
    files = sorted(PKG.rglob("*.py"))
    modules = {_module_name(f) for f in files}
    graph = {_module_name(f): _imports(f, modules) for f in files}
    # a parent package is imported before its submodules; that edge is not a cycle
    for m in graph:
        graph[m] = {d for d in graph[m] if not m.startswith(d + ".")}
    state, cycles = {}, []

    def visit(m, stack):
        state[m] = "open"
        for d in sorted(graph[m]):
            if state.get(d) == "open":
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [m, d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not cycles, f"import cycles: {cycles}"
    # the check sees the imports it must: scenarios imports walking, walking the types
    assert "safewbc_jax.walking" in graph["safewbc_jax.scenarios"]
    assert "safewbc_jax.scenario" in graph["safewbc_jax.walking"]


def test_module_sizes():
    long = []
    for f in sorted(PKG.rglob("*.py")):
        text = f.read_text()
        n = text.count("\n")
        if n > MAX_LINES and "\nSize:" not in text[:3000]:
            long.append(f"{f.relative_to(ROOT)} ({n} lines)")
    assert not long, f"modules over {MAX_LINES} lines without a stated reason: {long}"


def test_import_changes_no_jax_setting_and_the_model_asks_for_x64():
    code = ("import jax, safewbc_jax\n"
            "print('x64', jax.config.jax_enable_x64)\n"
            "import mujoco\n"
            "from safewbc_jax import paths, robot\n"
            "m = mujoco.MjModel.from_xml_path(str(paths.controller_xml()))\n"
            "try:\n"
            "    robot.from_mujoco(m)\n"
            "except RuntimeError as e:\n"
            "    print('refused', e)\n"
            "safewbc_jax.enable_x64()\n"
            "print('nv', robot.from_mujoco(m).nv, jax.config.jax_enable_x64)\n")
    env = {k: v for k, v in __import__("os").environ.items() if k != "JAX_ENABLE_X64"}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                       cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.splitlines()
    assert lines[0] == "x64 False"
    assert lines[1].startswith("refused") and "safewbc_jax.enable_x64()" in lines[1]
    assert lines[2] == "nv 36 True"


def test_every_module_is_in_the_what_is_here_table():
    """docs/index.md's "What is here" names every module of the package (by its file name,
    or its folder for solvers/ and sweeps/), so that the map stays true as modules come."""
    text = (ROOT / "docs" / "index.md").read_text()
    table = text[text.index("## What is here"):].split("\n## ", 1)[0]
    missing = [str(p.relative_to(ROOT)) for p in sorted(PKG.rglob("*.py"))
               if p.name != "__init__.py" and f"`{p.name}`" not in table
               and f"/{p.name}`" not in table and f"`safewbc_jax/{p.parent.name}/`" not in table]
    assert not missing, f"not in docs/index.md's 'What is here': {missing}"
