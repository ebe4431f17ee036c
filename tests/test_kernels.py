"""kernels.count: the working operations of a compiled program's entry computation."""

import jax
import jax.numpy as jnp
import pytest

from safewbc_jax.deploy import kernels

HLO = """HloModule m

fused_computation {
  p = f64[3]{0} parameter(0)
  ROOT s = f64[3]{0} sine(p)
}

ENTRY main {
  a = f64[3]{0} parameter(0)
  b = f64[3,3]{1,0} parameter(1)
  c = f64[] constant(1)
  f = f64[3]{0} fusion(a), kind=kLoop, calls=fused_computation
  d = f64[3]{0} dot(b, f), lhs_contracting_dims={1}, rhs_contracting_dims={0}
  e = f64[3]{0} bitcast(d)
  ROOT t = (f64[3]{0}) tuple(e)
}
"""


def test_count_text_counts_the_working_operations_of_entry_only():
    # the sine inside the fused computation is part of the fusion, not a kernel of its own;
    # parameters, constants, bitcasts and the tuple do no work
    assert kernels.count_text(HLO) == {"fusion": 1, "dot": 1, "total": 2}
    with pytest.raises(ValueError, match="ENTRY"):
        kernels.count_text("HloModule m\n")


def test_count_of_a_compiled_program_grows_with_its_unfusable_operations():
    x = jnp.ones(4)
    one = kernels.count(lambda a: jnp.sin(a) * 2.0 + 1.0, x)     # one elementwise chain
    assert one["total"] == 1, one
    m = jnp.ones((4, 4))
    # each dot of a chain whose next step needs the whole previous product is a kernel
    chain = kernels.count(jax.jit(lambda a, b: jnp.tanh(a @ jnp.tanh(a @ b)) @ b), m, m)
    assert chain.get("dot", 0) >= 2 and chain["total"] > one["total"], chain
