"""The XLA:CPU flags ``import safewbc_jax`` adds to ``XLA_FLAGS`` (``CPU_XLA_FLAGS``): added
where the user named none of them, the user's own setting kept, and XLA accepting them
(an unknown flag in XLA_FLAGS aborts the process when JAX starts its backend). Each case
in a fresh interpreter, whose environment the test sets."""

import math
import os
import subprocess
import sys

import pytest

import safewbc_jax

FLAG = "--xla_cpu_use_fusion_emitters"

CHILD = """
import os, sys
import safewbc_jax
import jax.numpy as jnp
print(repr(os.environ.get("XLA_FLAGS")))
print(float(jnp.sum(jnp.sin(jnp.arange(8.0)))))
"""


def _run(xla_flags):
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    if xla_flags is not None:
        env["XLA_FLAGS"] = xla_flags
    proc = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    flags, value = proc.stdout.splitlines()[-2:]
    return eval(flags), float(value)


@pytest.mark.parametrize("given, expected", [
    (None, f"{FLAG}=false"),
    ("--xla_force_host_platform_device_count=2",
     f"--xla_force_host_platform_device_count=2 {FLAG}=false"),
    # the user's own choice stays
    (f"--xla_force_host_platform_device_count=1 {FLAG}=true",
     f"--xla_force_host_platform_device_count=1 {FLAG}=true"),
])
def test_import_adds_the_cpu_flags_unless_named(given, expected):
    flags, value = _run(given)
    assert flags == expected
    # XLA took the flags (an unknown one aborts the child) and computed sum(sin(0..7)):
    # float32 (x64 off in the child), so to 1e-6
    assert value == pytest.approx(sum(math.sin(i) for i in range(8)), abs=1e-6)


def test_the_flags_are_xla_cpu_flags():
    """Only XLA:CPU reads them, so a program compiled for an accelerator is the one it
    would be without them."""
    assert safewbc_jax.CPU_XLA_FLAGS
    for f in safewbc_jax.CPU_XLA_FLAGS:
        assert f.startswith("--xla_cpu_") and "=" in f
