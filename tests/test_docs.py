"""The documentation site (mkdocs.yml, docs/) builds with warnings as errors, and its API
pages carry the functions they document: a renamed or removed function, a broken link or
anchor, or a docstring mkdocstrings cannot read breaks this test.

`python -m mkdocs build --strict` takes a few seconds (mkdocstrings reads the sources
statically: nothing is imported or compiled)."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# page -> identifiers that must each have a heading of their own on it
API = {
    "api/deploy": ["safewbc_jax.deploy.controller.Controller",
                   "safewbc_jax.deploy.controller.Controller.start",
                   "safewbc_jax.deploy.controller.Controller.step",
                   "safewbc_jax.deploy.controller.Controller.flush",
                   "safewbc_jax.control.step.Measurement", "safewbc_jax.deploy.compiled.Command",
                   "safewbc_jax.deploy.motors.MotorMap",
                   "safewbc_jax.deploy.checks.check_barrier_poles",
                   "safewbc_jax.deploy.compiled.CompiledStep"],
    "api/safesets": ["safewbc_jax.control.safesets.SafeSet", "safewbc_jax.control.safesets.load"],
    "api/tasks": ["safewbc_jax.control.tasks.Task"],
    "api/scenario": ["safewbc_jax.control.scenario.Scenario"],
    "api/rollout": ["safewbc_jax.sim.mjx.rollout.run_batch", "safewbc_jax.sim.mjx.rollout.BatchConfig",
                    "safewbc_jax.sim.mjx.rollout.default_params", "safewbc_jax.sim.mjx.rollout.Push",
                    "safewbc_jax.sim.mjx.rollout.export", "safewbc_jax.sim.mjx.rollout.memory_model"],
    "api/sweeps": ["safewbc_jax.sweeps.spec.load_spec", "safewbc_jax.sweeps.run.run_sweep",
                   "safewbc_jax.sweeps.table.read_table", "safewbc_jax.sweeps.report.make_report",
                   "safewbc_jax.sweeps.tune.tune_poles", "safewbc_jax.sweeps.stats.wilson_interval"],
    "api/solvers": ["safewbc_jax.solvers.solve_qp", "safewbc_jax.solvers.piqp_path.PiqpSolver",
                    "safewbc_jax.solvers.jax_qp.solve_batch", "safewbc_jax.solvers.result.SolveResult",
                    "safewbc_jax.solvers.status.SolveStatus",
                    "safewbc_jax.solvers.reduce.eliminate_equalities"],
}


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    out = tmp_path_factory.mktemp("site")
    res = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
         "-d", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"})
    assert res.returncode == 0, (
        f"mkdocs build --strict failed (rc {res.returncode}):\n{res.stdout}\n{res.stderr}")
    return out


def page(site: Path, name: str) -> str:
    return (site / name / "index.html").read_text()


@pytest.mark.parametrize("name", sorted(API))
def test_api_pages_document_their_functions(site, name):
    text = page(site, name)
    missing = [ident for ident in API[name] if f'id="{ident}"' not in text]
    assert not missing, f"{name}: no heading for {missing}"


def test_moved_pages_are_in_the_site(site):
    assert "h_ALIP(q)" in page(site, "equations")               # the table's last row, eq. 39
    bench = page(site, "benchmarks")                              # benchmarks/README.md
    for script in ("accelerator.py", "controller_step.py", "sweep_engines.py"):
        assert script in bench
    assert "Earlier measurements" in page(site, "changelog")     # CHANGELOG.md
    assert (site / "index.html").exists() and (site / "img" / "squat_com.png").exists()
