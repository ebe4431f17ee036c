"""The CPU paths stay on the CPU (``safewbc_jax.use_cpu``): ``safewbc run``, the mujoco
engine's driver and its workers select JAX's CPU platform before JAX starts, whatever the
environment asks for. Here the environment asks for CUDA (``JAX_PLATFORMS=cuda``), which
this machine cannot start: a process that did not select the CPU fails. The commands
themselves run under that environment in ``tests/test_user_scenario.py``."""

import os
import subprocess
import sys

CHILD = """
import os, sys
import safewbc_jax
if sys.argv[1] == "use_cpu":
    safewbc_jax.use_cpu()
import jax
import jax.numpy as jnp
print(jnp.ones(2).sum(), jax.devices()[0].platform, jax.config.jax_platforms)
safewbc_jax.use_cpu()      # again, after the backend is up on the CPU: nothing to do
"""


def _child(mode: str):
    env = {**os.environ, "JAX_PLATFORMS": "cuda", "JAX_TRACEBACK_FILTERING": "off"}
    return subprocess.run([sys.executable, "-c", CHILD, mode], env=env, capture_output=True,
                          text=True, timeout=120)


def test_use_cpu_overrides_an_accelerator_platform_in_the_environment():
    plain = _child("plain")
    # without it, JAX cannot start a backend at all (no CUDA here)
    assert plain.returncode != 0 and "xla_bridge" in plain.stderr, plain.stderr[-2000:]
    pinned = _child("use_cpu")
    assert pinned.returncode == 0, pinned.stderr[-2000:]
    assert pinned.stdout.split() == ["2.0", "cpu", "cpu"], pinned.stdout
