"""Training of the `recurrent` pose model (engine.pose_models.RecurrentPoseModel), offline, with JAX (build only).

    agentdress lab recurrent --database data/tshirt_default.h5 --pack data/tshirt_sequences.npz

Santesteban et al. 2019 learn their wrinkle regressor R_L as a GRU over the pose sequence. Here a small GRU (H
units) runs over the `regressor`'s standardised inputs and adds a correction to its standardised outputs (the PCA
coefficients of the rest-frame garment): the static regressor stays as it is, and the output layer starts at zero,
so training starts from the static model and the memory only has to learn what the motion adds. Data: the sequence
pack's clips at their 30 fps, cut where a frame lost the garment (RegressorSettings.max_offset), in windows of
`window` frames whose first `burn_in` frames only warm the state up (truncated backpropagation through time); Adam
on the mean squared error of the standardised coefficients (one scale for all of them: the rest-frame vertex error).
Deterministic given the seed on one CPU thread.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..engine.database import read_database, write_model
from ..engine.pose_models import Recurrent
from .regressor import coefficients_of, kept_frames, mlp_outputs, pack_data, standardized_inputs, store_in_database


@dataclass(frozen=True)
class RecurrentSettings:
    hidden: int = 16  # measured against 64 units (1,500 steps), which fit the training windows better and the
    # held-out sequences worse (README "The recurrent pose model")
    window: int = 40  # frames per training window (truncated backpropagation)
    burn_in: int = 10  # leading frames of a window that only warm the state up
    batch: int = 32
    steps: int = 400
    learning_rate: float = 2e-3
    seed: int = 0


def sequences(pack: dict, db, max_offset: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(canonical poses (T, B, 3), rest-frame garment (T, V, 3))] runs of consecutive frames of each clip, cut where
    a frame lost the garment."""
    frames = pack_data(pack, db, None)
    keep = np.zeros(len(frames.poses), dtype=bool)
    keep[kept_frames(pack, np.arange(len(keep)), max_offset)] = True
    clip, frame = np.asarray(pack["clip"]), np.asarray(pack["frame"])
    runs = []
    for c in np.unique(clip):
        rows = np.flatnonzero(clip == c)
        rows = rows[np.argsort(frame[rows])]
        start = 0
        for k in range(1, len(rows) + 1):
            if k == len(rows) or not keep[rows[k]] or frame[rows[k]] != frame[rows[k - 1]] + 1:
                run = rows[start:k][keep[rows[start:k]]]
                if len(run):
                    runs.append((frames.poses[run], frames.positions[run]))
                start = k
    return runs


def training_arrays(db, runs, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x (N, window, I), static outputs (N, window, G), targets (N, window, G)): windows every window/2 frames."""
    reg = db.regressor
    xs, statics, targets = [], [], []
    for poses, positions in runs:
        if len(poses) < window:
            continue
        x = standardized_inputs(reg, poses)
        static = mlp_outputs(reg, poses)
        coefficients = coefficients_of(reg, positions)
        target = (coefficients - reg.coefficient_mean) / reg.coefficient_scale
        for start in range(0, len(poses) - window + 1, window // 2):
            xs.append(x[start:start + window])
            statics.append(static[start:start + window])
            targets.append(target[start:start + window])
    return np.asarray(xs), np.asarray(statics), np.asarray(targets)


def train(db, runs, settings: RecurrentSettings, progress: bool = True) -> tuple[Recurrent, dict]:
    """The GRU correction trained on the runs (sequences()); returns it and a report (losses, windows)."""
    os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1")
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm

    jax.config.update("jax_enable_x64", True)
    x, static, target = training_arrays(db, runs, settings.window)
    if len(x) == 0:
        raise ValueError(f"no sequence holds {settings.window} consecutive frames")
    n_in, n_out, h = x.shape[2], target.shape[2], settings.hidden
    key = jax.random.PRNGKey(settings.seed)
    k1, k2 = jax.random.split(key)
    bound = 1.0 / np.sqrt(h)
    params = {"input_weights": jax.random.uniform(k1, (n_in, 3 * h), minval=-bound, maxval=bound),
              "state_weights": jax.random.uniform(k2, (h, 3 * h), minval=-bound, maxval=bound),
              "bias": jnp.zeros(3 * h), "output_weights": jnp.zeros((h, n_out)), "output_bias": jnp.zeros(n_out)}

    def step_state(p, state, xt):
        a = xt @ p["input_weights"] + p["bias"]
        s = state @ p["state_weights"]
        z = jax.nn.sigmoid(a[..., :h] + s[..., :h])
        r = jax.nn.sigmoid(a[..., h:2 * h] + s[..., h:2 * h])
        n = jnp.tanh(a[..., 2 * h:] + r * s[..., 2 * h:])
        new = (1.0 - z) * n + z * state
        return new, new

    def loss(p, xb, sb, tb):
        _, states = jax.lax.scan(lambda c, xt: step_state(p, c, xt), jnp.zeros((xb.shape[0], h)),
                                 jnp.swapaxes(xb, 0, 1))
        out = jnp.swapaxes(states, 0, 1) @ p["output_weights"] + p["output_bias"] + sb
        return jnp.mean((out - tb)[:, settings.burn_in:] ** 2)

    @jax.jit
    def update(p, m, v, t, xb, sb, tb):
        value, grads = jax.value_and_grad(loss)(p, xb, sb, tb)
        m = jax.tree_util.tree_map(lambda a, g: 0.9 * a + 0.1 * g, m, grads)
        v = jax.tree_util.tree_map(lambda a, g: 0.999 * a + 0.001 * g * g, v, grads)
        scale = settings.learning_rate * jnp.sqrt(1 - 0.999 ** t) / (1 - 0.9 ** t)
        p = jax.tree_util.tree_map(lambda w, a, b: w - scale * a / (jnp.sqrt(b) + 1e-8), p, m, v)
        return p, m, v, value

    m = jax.tree_util.tree_map(jnp.zeros_like, params)
    v = jax.tree_util.tree_map(jnp.zeros_like, params)
    rng = np.random.default_rng(settings.seed)
    static_loss = float(np.mean((static - target)[:, settings.burn_in:] ** 2))
    losses = []
    for t in tqdm(range(1, settings.steps + 1), desc="recurrent", unit="step", disable=not progress):
        batch = rng.choice(len(x), size=min(settings.batch, len(x)), replace=False)
        params, m, v, value = update(params, m, v, t, x[batch], static[batch], target[batch])
        losses.append(float(value))
    final = float(loss(params, x, static, target))
    report = {"windows": int(len(x)), "window": settings.window, "runs": len(runs),
              "static_rms": float(np.sqrt(static_loss)), "recurrent_rms": float(np.sqrt(final)),
              "last_batch_losses": losses[-5:], "settings": asdict(settings),
              "note": "rms in standardised coefficients (x coefficient_scale: metres of rest-frame vertex error)"}
    arrays = {name: np.asarray(params[name], dtype=np.float32) for name in params}
    return Recurrent(**arrays, info=report), report


def main(argv=None) -> int:
    from .regressor import RegressorSettings
    from .sequences import load_sequence_pack

    parser = argparse.ArgumentParser(prog="agentdress lab recurrent", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--database", required=True, help="a database with pose_model/regressor")
    parser.add_argument("--pack", required=True, help="the garment's beta0 sequence pack")
    defaults = RecurrentSettings()
    parser.add_argument("--hidden", type=int, default=defaults.hidden)
    parser.add_argument("--steps", type=int, default=defaults.steps)
    parser.add_argument("--seed", type=int, default=defaults.seed)
    args = parser.parse_args(argv)
    settings = RecurrentSettings(hidden=args.hidden, steps=args.steps, seed=args.seed)
    db = read_database(args.database)
    if db.regressor is None:
        raise SystemExit(f"{args.database}: no pose_model/regressor to add memory to; run `agentdress lab regressor`")
    runs = sequences(load_sequence_pack(args.pack), db, RegressorSettings().max_offset)
    recurrent, report = train(db, runs, settings)
    store_in_database(args.database, lambda h5: write_model(h5, "recurrent", recurrent))
    print(json.dumps({"database": str(args.database), **report}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
