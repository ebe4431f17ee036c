"""safewbc-jax: safe whole-body task-space control (A-ECBF inverse-dynamics QP) for Digit.

The controller's robot terms and QPs are float64: call ``safewbc_jax.enable_x64()`` once,
before building a model or a controller (the ``safewbc`` command and the examples do).
Importing the package changes no JAX setting; where 64-bit floats are needed and off,
``robot.from_mujoco`` (every path builds its model there) raises an error that says so.
Arrays made with an explicit float32 dtype (the accelerator option of the batched path)
stay float32. ``JAX_ENABLE_X64=1`` in the environment does the same as ``enable_x64()``.

Importing it sets two defaults for the libraries under JAX, each unless the user set it:
one OpenBLAS thread, and XLA:CPU's classic fusion emitters (``CPU_XLA_FLAGS``).
"""

from typing import TYPE_CHECKING, Any

from safewbc_jax.base.runtime import (CPU_XLA_FLAGS, add_xla_flags, enable_x64, require_x64,
                                      use_compile_cache, use_cpu)

# The public API: each name is imported from its module at first use (PEP 562), so that
# ``import safewbc_jax`` stays light (the command line checks its options before JAX and
# MuJoCo load) and no module of the package imports the package's top. "module:name" is a
# module's attribute; a bare module path is the module itself (``robot``, ``spatial``,
# ``outputs``: what a user's safe set or task is written with).
_API = {
    "Controller": "safewbc_jax.deploy.controller:Controller",
    "Command": "safewbc_jax.deploy.compiled:Command",
    "MotorMap": "safewbc_jax.deploy.motors:MotorMap",
    "Measurement": "safewbc_jax.control.step:Measurement",
    "ControllerParams": "safewbc_jax.control.params:ControllerParams",
    "Scenario": "safewbc_jax.control.scenario:Scenario",
    "Task": "safewbc_jax.control.tasks:Task",
    "SafeSet": "safewbc_jax.control.safesets:SafeSet",
    "get_scenario": "safewbc_jax.scenarios:get_scenario",
    "BatchConfig": "safewbc_jax.sim.mjx.plant:BatchConfig",
    "BatchError": "safewbc_jax.sim.mjx.plant:BatchError",
    "default_params": "safewbc_jax.sim.mjx.plant:default_params",
    "run_batch": "safewbc_jax.sim.mjx.rollout:run_batch",
    "export": "safewbc_jax.sim.mjx.rollout:export",
    "Push": "safewbc_jax.control.push:Push",
    "load_at_stand": "safewbc_jax.sim.mujoco_loop:load_at_stand",
    "run_scenario": "safewbc_jax.app.runner:run_scenario",
    "format_summary": "safewbc_jax.app.runner:format_summary",
    "QP": "safewbc_jax.solvers.problem:QP",
    "SolveResult": "safewbc_jax.solvers.result:SolveResult",
    "solve_qp": "safewbc_jax.solvers:solve_qp",
    "load_spec": "safewbc_jax.sweeps.spec:load_spec",
    "run_sweep": "safewbc_jax.sweeps.run:run_sweep",
    "read_table": "safewbc_jax.sweeps.table:read_table",
    "make_report": "safewbc_jax.sweeps.report:make_report",
    "tune": "safewbc_jax.sweeps.tuning:tune",
    "robot": "safewbc_jax.model.robot",
    "spatial": "safewbc_jax.model.spatial",
    "outputs": "safewbc_jax.control.outputs",
}

__all__ = ["CPU_XLA_FLAGS", "add_xla_flags", "enable_x64", "require_x64", "use_compile_cache",
           "use_cpu", "Controller", "Command", "MotorMap", "Measurement", "ControllerParams",
           "Scenario", "Task", "SafeSet", "get_scenario", "BatchConfig", "BatchError",
           "default_params", "run_batch", "export", "Push", "load_at_stand", "run_scenario",
           "format_summary", "QP", "SolveResult", "solve_qp", "load_spec", "run_sweep",
           "read_table", "make_report", "tune", "robot", "spatial", "outputs"]


def __getattr__(name: str) -> Any:
    if name in _API:
        import importlib

        where, _, attr = _API[name].partition(":")
        module = importlib.import_module(where)
        value = getattr(module, attr) if attr else module
        globals()[name] = value
        return value
    raise AttributeError(f"module 'safewbc_jax' has no attribute {name!r}")


if TYPE_CHECKING:
    from safewbc_jax.app.runner import format_summary, run_scenario
    from safewbc_jax.control import outputs
    from safewbc_jax.control.params import ControllerParams
    from safewbc_jax.control.safesets import SafeSet
    from safewbc_jax.control.scenario import Scenario
    from safewbc_jax.control.step import Measurement
    from safewbc_jax.control.tasks import Task
    from safewbc_jax.deploy.compiled import Command
    from safewbc_jax.deploy.controller import Controller
    from safewbc_jax.deploy.motors import MotorMap
    from safewbc_jax.model import robot, spatial
    from safewbc_jax.scenarios import get_scenario
    from safewbc_jax.sim.mjx.plant import BatchConfig, BatchError, default_params
    from safewbc_jax.sim.mjx.rollout import export, run_batch
    from safewbc_jax.sim.mujoco_loop import load_at_stand
    from safewbc_jax.control.push import Push
    from safewbc_jax.solvers import solve_qp
    from safewbc_jax.solvers.problem import QP
    from safewbc_jax.solvers.result import SolveResult
    from safewbc_jax.sweeps.report import make_report
    from safewbc_jax.sweeps.run import run_sweep
    from safewbc_jax.sweeps.spec import load_spec
    from safewbc_jax.sweeps.table import read_table
    from safewbc_jax.sweeps.tuning import tune
