"""``benchmarks/iree_step.py`` compiles the deployed step's StableHLO with IREE only after
putting an optimization barrier on every concatenate operand. Its claim is that the
exported function is unchanged. IREE is not installed in CI; XLA is the independent
check. The rewritten module must parse and verify, and it must give the exported
function's outputs. A barrier returns its operand as it is, but it also stops XLA from
fusing across it, and a sum or a sine compiled in another fusion may round differently in
the last bits on some CPU. Hence 1e-12 relative and absolute, on outputs of order 1-100:
~1e4 ulp, far above such rounding and far below what a misplaced operand gives (O(1)). The
operands of each concatenate have different values and shapes: an operand that went to the
wrong place, or lost its type, fails here.
"""

import dataclasses
import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "iree_step.py"


def _script():
    spec = importlib.util.spec_from_file_location("iree_step", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _f(x, y):
    a = jnp.concatenate([x[:, :2] * 2.0, y, jnp.sin(x[:, 2:])], axis=1)   # 3 operands, dim 1
    b = jnp.concatenate([a.sum(0), x[0], y[:, 0]])                          # 1-D
    return jnp.stack([a[:, 0], a[:, 3]]), b                                   # stack: dim 0


def test_barriers_on_concatenates_keep_the_function():
    from jax._src.export import _export
    from jax._src.interpreters import mlir
    from jax._src.lib.mlir import ir

    x = np.arange(12.0).reshape(4, 3) - 5.0
    y = np.array([[0.5], [-1.5], [2.0], [7.0]])
    exported = jax.export.export(jax.jit(_f))(x, y)
    text = exported.mlir_module()
    rewritten, n = _script().barrier_concatenates(text)
    assert n == text.count("stablehlo.concatenate") == 3
    assert rewritten.count("stablehlo.optimization_barrier") == 3 + 3 + 2
    with mlir.make_ir_context():
        module = ir.Module.parse(rewritten)
        assert module.operation.verify()
        blob = _export._module_to_bytecode(module)
    again = dataclasses.replace(exported, mlir_module_serialized=blob)
    for got, want in zip(again.call(x, y), _f(x, y)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-12, atol=1e-12)
