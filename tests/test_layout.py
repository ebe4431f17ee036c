"""The package's layout: folders by layer, each importing only the layers below it; no
import cycle between its modules; and importing it changes no JAX setting."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "safewbc_jax"
# the package's folders, lowest layer first (docs/index.md, "What is here")
LAYERS = ("base", "model", "solvers", "control", "scenarios", "deploy", "ui", "sim", "sweeps",
          "app")


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
    assert "safewbc_jax.control.walking" in graph["safewbc_jax.scenarios"]
    assert "safewbc_jax.control.scenario" in graph["safewbc_jax.control.walking"]


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.index(parts[1]) if len(parts) > 1 and parts[1] in LAYERS else None


def test_each_folder_imports_only_the_layers_below_it():
    """A module imports its own layer's modules and those of lower layers, never a higher
    layer's nor the package's top (``safewbc_jax/__init__.py``, the public API, which
    imports from them), lazily inside a function included."""
    files = sorted(PKG.rglob("*.py"))
    modules = {_module_name(f) for f in files}
    unknown = sorted({m.split(".")[1] for m in modules if "." in m} - set(LAYERS))
    assert not unknown, f"folders or modules outside the layers {LAYERS}: {unknown}"
    wrong = []
    for f in files:
        me = _module_name(f)
        if me == "safewbc_jax":
            continue
        for d in _imports(f, modules):
            if me.startswith(d + "."):
                continue        # a parent package, imported before its submodules
            if _layer(d) > _layer(me):
                wrong.append(f"{me} imports {d}")
        for node in ast.walk(ast.parse(f.read_text())):   # the top: its API, not a folder
            if isinstance(node, ast.Import) and any(a.name == "safewbc_jax" for a in node.names):
                wrong.append(f"{me} imports safewbc_jax")
            if isinstance(node, ast.ImportFrom) and node.module == "safewbc_jax":
                wrong += [f"{me} imports safewbc_jax.{a.name}" for a in node.names
                          if f"safewbc_jax.{a.name}" not in modules]
    assert not wrong, "imports against the layers: " + "; ".join(wrong)


def test_the_top_holds_the_api_and_folders():
    top = sorted(p.name for p in PKG.glob("*.py"))
    assert top == ["__init__.py"], top
    folders = sorted(p.name for p in PKG.iterdir() if p.is_dir() and p.name != "__pycache__")
    assert folders == sorted(LAYERS), folders


def test_the_public_api_resolves():
    import safewbc_jax

    assert set(safewbc_jax._API) <= set(safewbc_jax.__all__)
    for name in safewbc_jax.__all__:
        assert getattr(safewbc_jax, name) is not None, name


def test_import_changes_no_jax_setting_and_the_model_asks_for_x64():
    code = ("import jax, safewbc_jax\n"
            "print('x64', jax.config.jax_enable_x64)\n"
            "import mujoco\n"
            "from safewbc_jax.base import paths\n"
            "from safewbc_jax.model import robot\n"
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


def test_every_folder_and_module_is_in_the_what_is_here_table():
    """docs/index.md's "What is here" has one row per folder of the package, in the layers'
    order, and names each of its modules, so that the map stays true as modules come."""
    text = (ROOT / "docs" / "index.md").read_text()
    table = text[text.index("## What is here"):].split("\n## ", 1)[0]
    rows = [line.split("`")[1] for line in table.splitlines()
            if line.startswith("| `safewbc_jax/")]
    assert rows == [f"safewbc_jax/{f}/" for f in LAYERS], rows
    missing = [str(p.relative_to(ROOT)) for p in sorted(PKG.rglob("*.py"))
               if p.name != "__init__.py" and f"`{p.name}`" not in table]
    assert not missing, f"not in docs/index.md's 'What is here': {missing}"


# attributes with a leading underscore that are public by convention (NamedTuple's API,
# os._exit), and MJX's Data._impl, where MJX keeps its JAX implementation's contacts and
# constraint forces
PUBLIC_UNDERSCORE = {"_replace", "_fields", "_asdict", "_make", "_field_defaults", "_exit",
                     "_impl"}


def test_no_module_touches_another_objects_private_attributes():
    """An attribute with a leading underscore is read or written only through ``self`` or
    ``cls``: no object reaches into another's private fields."""
    found = []
    for path in sorted(PKG.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Attribute) and node.attr.startswith("_")
                    and not node.attr.startswith("__") and node.attr not in PUBLIC_UNDERSCORE
                    and not (isinstance(node.value, ast.Name)
                             and node.value.id in ("self", "cls"))):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert not found, "\n".join(found)


def test_every_package_folder_is_installed():
    """A non-editable install (the quick start's ``pip install .``) ships exactly the
    packages pyproject.toml lists: each folder of the package must be among them."""
    import tomllib

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())
                 ["tool"]["setuptools"]["packages"])
    found = {_module_name(p) for p in PKG.rglob("__init__.py")}
    assert found <= listed, f"not in pyproject.toml's packages: {sorted(found - listed)}"


def test_the_controller_keeps_one_robot_only():
    """``deploy/controller.py`` is one robot's controller over a ``CompiledStep`` (issue 51:
    at most 350 lines); the compiled step and its lanes live in ``deploy/compiled.py``."""
    text = (PKG / "deploy" / "controller.py").read_text()
    assert len(text.splitlines()) <= 350
    assert "def admit" not in text and "def finish" not in text and "staticmethod" not in text
