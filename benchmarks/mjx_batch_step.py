"""Bare batched MJX physics of the Digit simulation model: ``jax.vmap(mjx.step)``.

Prints compile time and physics steps per second; ``--json`` prints one JSON object as the
last line. Also the check for the XLA CPU hang seen at batch 256 (shared/digit/README.md):
the foundation test runs this script in a subprocess with a timeout.

    python benchmarks/mjx_batch_step.py --batch 256 --steps 100 --json
"""

from __future__ import annotations

import argparse
import json
import time


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--steps", type=int, default=100)
    ap.add_argument("--model", default=None, help="MJCF path (default models/scene.xml)")
    ap.add_argument("--dtype", choices=("float64", "float32"), default="float64",
                    help="float64 is the CPU default of this project; float32 for accelerators")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if args.batch < 1 or args.steps < 1:
        ap.error("--batch and --steps must be positive")

    import jax

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    import jax.numpy as jnp
    import mujoco

    from safewbc_jax.base import paths
    from safewbc_jax.control import precision
    from safewbc_jax.sim.mjx.imports import import_mjx

    mjx = import_mjx()

    m = mujoco.MjModel.from_xml_path(str(args.model or paths.scene_xml()))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.key("stand").id)
    mx = mjx.put_model(m)
    dx = mjx.put_data(m, d)
    key = jax.random.PRNGKey(0)
    noise = 1e-3 * jax.random.normal(key, (args.batch, m.nv))
    batch = jax.vmap(lambda dq: dx.replace(qvel=dx.qvel + dq))(noise)

    # precision.physics gives each leaf back in the dtype it came in (under x64 mjx.step
    # returns int64 contact indices where put_data made int32 ones), so the data can be the
    # scan's carry and the program holds mjx.step once
    step = jax.vmap(precision.physics(mjx.step, args.dtype), in_axes=(None, 0))

    def rollout(data):
        return jax.lax.scan(lambda dd, _: (step(mx, dd), None), data, None,
                            length=args.steps)[0]

    fn = jax.jit(rollout)
    t0 = time.perf_counter()
    compiled = fn.lower(batch).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = compiled(batch)
    jax.block_until_ready(out)
    t_run = time.perf_counter() - t0
    res = {
        "batch": args.batch, "steps": args.steps, "compile_s": round(t_compile, 2),
        "run_s": round(t_run, 3), "physics_steps_per_s": round(args.batch * args.steps / t_run, 1),
        "finite": bool(jnp.all(jnp.isfinite(out.qpos))),
        "min_base_height": float(jnp.min(out.qpos[:, 2])),
        "x64": bool(jax.config.jax_enable_x64), "backend": jax.default_backend(),
    }
    if args.json:
        print(json.dumps(res))
    else:
        for k, v in res.items():
            print(f"{k:>22}: {v}")
    return res


if __name__ == "__main__":
    main()
