"""The README's examples work as written, without running a simulation.

- Every fenced ```python block compiles; those that do not compile a controller or a closed
  loop are executed. The Deployment API block is executed by
  tests/test_deploy.py::test_readme_example_runs_as_written (slow), the batched-path block
  takes minutes: both only compile here.
- Every `safewbc ...` command in a ```bash block parses with the CLI's own parser (every
  option and value exists), and the files it names are in the repository or written by a
  command before it in the README. `python FILE` and `python -m MODULE` name something that
  exists.
- Relative links and the picture point at files that exist, and the README stays a short
  user's document (at most 300 lines).
"""

import importlib.util
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"

# blocks that compile a controller or a closed loop: compiled, not executed, here
LONG = ("Controller(", "run_batch(")


def blocks(lang: str) -> list[str]:
    return re.findall(rf"^```{lang}\n(.*?)^```", README.read_text(), re.S | re.M)


def commands() -> list[list[str]]:
    """The shell commands of the ```bash blocks, in order, each as its argument list
    (comments dropped, `&&` chains split)."""
    out = []
    for block in blocks("bash"):
        for line in block.replace("\\\n", " ").splitlines():
            words = shlex.split(line, comments=True)
            cmd = []
            for w in words + ["&&"]:
                if w in ("&&", ";", "||"):
                    if cmd:
                        out.append(cmd)
                    cmd = []
                else:
                    cmd.append(w)
    return out


PY_BLOCKS = blocks("python")


def test_readme_has_examples():
    assert len(PY_BLOCKS) >= 3
    assert sum(c[0] == "safewbc" for c in commands()) >= 5


@pytest.mark.parametrize("i", range(len(PY_BLOCKS)))
def test_python_block(i):
    code = PY_BLOCKS[i]
    compiled = compile(code, f"README.md (python block {i})", "exec")
    if any(marker in code for marker in LONG):
        return
    import safewbc_jax

    safewbc_jax.enable_x64()
    exec(compiled, {"__name__": f"readme_block_{i}"})


def test_safewbc_commands_parse(capsys):
    from safewbc_jax.app.cli import _join_dash_values, build_parser

    parser = build_parser()
    written = set()                      # --out of the commands before
    checked = 0
    for cmd in commands():
        if cmd[0] != "safewbc":
            continue
        text = " ".join(cmd)
        try:
            args = parser.parse_args(_join_dash_values(cmd[1:]))
        except SystemExit:
            pytest.fail(f"README: `{text}` does not parse:\n{capsys.readouterr().err}")
        inputs = []
        if args.command in ("sweep", "tune", "tune-poles"):
            inputs.append(args.spec)
        if args.command == "report":
            inputs.append(args.dir)
        if args.command == "run":
            inputs += [ref.split(":")[0] for ref in args.safe_set]
            if args.params:
                inputs.append(args.params)
        for path in inputs:
            assert (ROOT / path).exists() or path in written, (
                f"README: `{text}` reads {path}, which is neither in the repository nor "
                f"written by a command before it")
        if getattr(args, "out", None):
            written.add(args.out)
        if args.command in ("tune", "tune-poles"):      # and the folder of its generations
            suffix = "_tune" if args.command == "tune" else "_rounds"
            written.add(args.work or args.out.removesuffix(".toml") + suffix)
        checked += 1
    assert checked


def test_python_commands_name_what_exists():
    for cmd in commands():
        if not cmd[0].startswith("python"):
            continue
        if cmd[1] == "-m":
            if cmd[2] == "venv":
                continue
            assert importlib.util.find_spec(cmd[2]) is not None, f"README: `{' '.join(cmd)}`"
        elif cmd[1].endswith(".py"):
            assert (ROOT / cmd[1]).exists(), f"README: `{' '.join(cmd)}`"


def test_links_and_picture_exist():
    text = README.read_text()
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert any(t.endswith(".png") for t in targets), "the README shows one picture"
    missing = [t for t in targets if "://" not in t and not (ROOT / t).exists()]
    assert not missing, f"README links to missing files: {missing}"


def test_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines; the guide's details belong in docs/"
