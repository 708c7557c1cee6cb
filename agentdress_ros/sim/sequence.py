"""Dynamic ground truth: a garment simulated along a whole motion clip, with the body animated every substep.

`simulate_sequence(motion, garment, beta, folder)` resamples the clip to `SequenceSettings.fps` (30 by default; the
CMU clips are 120 fps), settles the garment on the first frame with an animated drape (the body carried from the
rest pose into the first pose), then runs the clip: per mocap frame `settings.drape.fps / fps` simulation frames,
the body surface moving linearly between consecutive mocap frames over every substep (`ClothSim.frame`).

Root motion is included: the simulation runs in the world frame, so the cloth feels the body's accelerations
(a walk's sway, a jump's landing). Each frame's pose, root translation and root velocity are stored beside the
cloth, so a learned model can unpose the garment into the rest frame or condition on the motion.

Resumable by chunks: every `chunk_frames` mocap frames are written atomically to `<folder>/chunk_NNNN.npz` with the
cloth positions of each frame and the simulation state (positions and velocities, float32 as newton holds them)
at the chunk's end. A rerun continues after the last complete chunk, losing at most one chunk, and produces the
same frames as an uninterrupted run (the state is exactly what the solver carries from step to step).
"""
from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .settings import DrapeSettings


@dataclass(frozen=True)
class SequenceSettings:
    """fps: mocap frames per second after resampling (30). chunk_frames: mocap frames per checkpoint (30).
    ramp_frames: simulation frames carrying the body from rest into the first pose (30). settle_frames: most
    frames settling there before the clip starts (120). drape: the cloth and solver settings; its
    velocity_retention applies only while settling (the clip itself runs without artificial drag).
    max_body_step: m; a simulation frame in which some body vertex would move farther than this in one substep
    gets as many more substeps as keep it within (0: always drape.substeps). A fast limb otherwise passes through
    the cloth's contact layer in one step (at 16 substeps and 60 fps, 9 m/s is 9 mm a step)."""

    fps: float = 30.0
    chunk_frames: int = 30
    ramp_frames: int = 30
    settle_frames: int = 120
    drape: DrapeSettings = field(default_factory=DrapeSettings)
    max_body_step: float = 0.0

    def key(self) -> str:
        fields = asdict(self)
        if not self.max_body_step:  # sequences from before the knob keep their key
            fields.pop("max_body_step")
        if not self.drape.warm_ramp_frames:  # nor does a drape knob sequences never use change it
            fields["drape"].pop("warm_ramp_frames")
        return json.dumps(fields, sort_keys=True)

    def substeps(self, body_from, body_to) -> int:
        """Substeps for one simulation frame in which the body surface moves from body_from to body_to (N, 3)."""
        if not self.max_body_step:
            return self.drape.substeps
        step = float(np.sqrt(np.max(np.einsum("ij,ij->i", body_to - body_from, body_to - body_from))))
        return max(self.drape.substeps, int(np.ceil(step / self.max_body_step - 1e-9)))  # 1e-9: not 26 for 25.0000001


def resample(motion, fps: float):
    """(rotvecs (F, B, 3), root_translation (F, 3)) of a Motion taken every round(motion.fps / fps) frames."""
    step = max(1, int(round(motion.fps / fps)))
    return motion.rotvecs[::step], motion.root_translation[::step]


def _save_atomic(path: Path, **arrays) -> None:
    partial = path.with_name(path.name + f".{os.getpid()}.partial")
    with open(partial, "wb") as handle:
        np.savez(handle, **arrays)
    os.replace(partial, path)


def sequence_key(settings: SequenceSettings, beta, motion_name: str, n_frames: int, garment, rotvecs=None,
                 roots=None) -> str:
    """The key every chunk of a sequence carries: a resumed run continues only chunks written under the same one.
    With the resampled rotvecs (F, B, 3) and roots (F, 3), it also holds their digest, so a clip whose motion was
    processed otherwise (a repaired capture flip) is not continued from chunks of the old motion."""
    key = {"settings": settings.key(), "beta": np.round(np.asarray(beta, float), 6).tolist(), "motion": motion_name,
           "frames": n_frames, "garment": garment.name, "vertices": garment.n_vertices}
    if rotvecs is not None:
        digest = hashlib.sha256(np.ascontiguousarray(rotvecs, dtype=np.float64).tobytes())
        digest.update(np.ascontiguousarray(roots, dtype=np.float64).tobytes())
        key["motion_digest"] = digest.hexdigest()[:16]
    return json.dumps(key)


def _chunks_done(folder: Path, key: str) -> int:
    """Number of consecutive complete chunks in folder written under `key` (a chunk of another key stops it)."""
    count = 0
    while (folder / f"chunk_{count:04d}.npz").is_file():
        with np.load(folder / f"chunk_{count:04d}.npz") as data:
            if str(data["key"]) != key:
                raise ValueError(f"{folder}: chunk {count} was simulated with other settings or another motion; "
                                 "delete the folder or choose another one")
        count += 1
    return count


def simulate_sequence(motion, garment, beta, folder, settings: SequenceSettings | None = None, body=None,
                      max_chunks: int | None = None, progress: bool = True) -> dict:
    """Simulate `garment` on the body of shape `beta` (6,) along `motion` (a skeleton.Motion retargeted to that
    body); writes chunks into `folder` and returns {"frames", "chunks", "seconds", "max_cloth_speed",
    "max_body_speed", "frames_more_substeps", "max_substeps"} over the chunks computed in this call (max_chunks
    stops early, for tests)."""
    from tqdm import tqdm

    from ..body import AnnyBody
    from .cloth import ClothSim
    from ..body import visible_body
    from .posing import posed_surfaces, ramp_poses

    s = SequenceSettings() if settings is None else settings
    body = AnnyBody() if body is None else body
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    shape = body.shape(beta)
    rotvecs, roots = resample(motion, s.fps)
    n_frames = len(rotvecs)
    n_chunks = -(-n_frames // s.chunk_frames)
    key = sequence_key(s, beta, motion.name, n_frames, garment, rotvecs, roots)
    (folder / "sequence.json").write_text(json.dumps({"key": json.loads(key), "chunks": n_chunks}, indent=1))
    done = _chunks_done(folder, key)
    rest = garment.rest_vertices(body, shape)
    _, faces = visible_body(body)
    pin = garment.pinned
    sim_per_frame = max(1, int(round(s.drape.fps / s.fps)))
    start = time.perf_counter()
    stats = {"frames": 0, "chunks": 0, "max_cloth_speed": 0.0, "max_body_speed": 0.0, "frames_more_substeps": 0,
             "max_substeps": s.drape.substeps}
    if done >= n_chunks:
        return {**stats, "seconds": 0.0}

    first_body, first_garment = posed_surfaces(body, garment, shape, rotvecs[:1], roots[:1])
    if done == 0:  # settle on the first frame: carry the body from rest into it, then let the cloth come to rest
        ramp = ramp_poses(rotvecs[0], s.ramp_frames)
        ramp_roots = np.linspace(0.0, 1.0, s.ramp_frames, endpoint=False)[:, None] * roots[0][None]
        path, path_garments = posed_surfaces(body, garment, shape, ramp, ramp_roots)
        sim = ClothSim(rest, garment.faces, path[0], faces, s.drape, rest=rest, pinned=pin)
        for k in range(1, s.ramp_frames + 1):
            target = path[k] if k < s.ramp_frames else first_body[0]
            pins = (path_garments[k] if k < s.ramp_frames else first_garment[0])[pin]
            sim.frame(body_to=target, pinned_to=pins)
            sim.scale_velocities(s.drape.velocity_retention)
        previous = sim.positions()
        for _ in range(s.settle_frames):
            current = sim.frame()
            sim.scale_velocities(s.drape.velocity_retention)
            speed = np.linalg.norm(current - previous, axis=1) * s.drape.fps
            previous = current
            if np.percentile(speed, s.drape.speed_percentile) < s.drape.speed_threshold:
                break
        last_body, last_pins = first_body[0], first_garment[0][pin]
        sim = _resume(rest, garment, last_body, faces, s, pin, sim.states[0].particle_q.numpy(),
                      sim.states[0].particle_qd.numpy(), last_pins)
    else:
        with np.load(folder / f"chunk_{done - 1:04d}.npz") as data:
            state = (data["state_q"], data["state_qd"])
            last = int(data["frames"][-1])
        last_body, last_garment = posed_surfaces(body, garment, shape, rotvecs[last:last + 1], roots[last:last + 1])
        last_body, last_pins = last_body[0], last_garment[0][pin]
        sim = _resume(rest, garment, last_body, faces, s, pin, *state, last_pins)

    chunks = range(done, n_chunks if max_chunks is None else min(n_chunks, done + max_chunks))
    bar = tqdm(total=n_frames, initial=done * s.chunk_frames, desc=f"{motion.name} {garment.name}", unit="frame",
               disable=not progress)
    for c in chunks:
        frames = np.arange(c * s.chunk_frames, min(n_frames, (c + 1) * s.chunk_frames))
        bodies, garments = posed_surfaces(body, garment, shape, rotvecs[frames], roots[frames])
        positions = np.empty((len(frames),) + rest.shape, dtype=np.float32)
        cloth_speed = np.zeros(len(frames))
        body_speed = np.zeros(len(frames))
        for i, frame in enumerate(frames):
            if frame == 0:  # the settled start is frame 0
                positions[i] = sim.positions()
                continue
            before = sim.positions()
            substeps = s.substeps(last_body, last_body + (bodies[i] - last_body) / sim_per_frame)
            stats["frames_more_substeps"] += substeps > s.drape.substeps
            stats["max_substeps"] = max(stats["max_substeps"], substeps)
            for k in range(1, sim_per_frame + 1):
                alpha = k / sim_per_frame
                current = sim.frame(body_to=last_body + alpha * (bodies[i] - last_body),
                                    pinned_to=last_pins + alpha * (garments[i][pin] - last_pins), substeps=substeps)
            if not np.isfinite(current).all():
                raise RuntimeError(f"{motion.name}: the cloth diverged at frame {frame}")
            positions[i] = current
            cloth_speed[i] = np.linalg.norm(current - before, axis=1).max() * s.fps
            body_speed[i] = np.linalg.norm(bodies[i] - last_body, axis=1).max() * s.fps
            last_body, last_pins = bodies[i], garments[i][pin]
            bar.update()
        root_velocity = np.gradient(roots, axis=0)[frames] * s.fps if n_frames > 1 else np.zeros((len(frames), 3))
        state_q, state_qd = sim.states[0].particle_q.numpy(), sim.states[0].particle_qd.numpy()
        _save_atomic(folder / f"chunk_{c:04d}.npz", key=np.array(key), frames=frames,
                     positions=positions, rotvecs=rotvecs[frames].astype(np.float32),
                     root_translation=roots[frames].astype(np.float32),
                     root_velocity=root_velocity.astype(np.float32), state_q=state_q, state_qd=state_qd,
                     cloth_speed=cloth_speed.astype(np.float32), body_speed=body_speed.astype(np.float32))
        # Continue from a fresh simulation, exactly as a resumed run does: newton keeps state beyond positions and
        # velocities (the collider's refitted tree, solver scratch), which moved frames by ~1e-6 m otherwise.
        sim = _resume(rest, garment, last_body, faces, s, pin, state_q, state_qd, last_pins)
        stats["frames"] += len(frames)
        stats["chunks"] += 1
        stats["max_cloth_speed"] = max(stats["max_cloth_speed"], float(cloth_speed.max()))
        stats["max_body_speed"] = max(stats["max_body_speed"], float(body_speed.max()))
    bar.close()
    return {**stats, "seconds": time.perf_counter() - start}


def _resume(rest, garment, body_vertices, body_faces, settings: SequenceSettings, pinned, q, qd, pinned_positions):
    """A fresh ClothSim at a checkpoint: the body still at body_vertices, the cloth at (q, qd)."""
    from .cloth import ClothSim

    sim = ClothSim(rest, garment.faces, body_vertices, body_faces, settings.drape, rest=rest, pinned=pinned)
    sim.set_state(q, qd)
    sim.pinned_positions = np.asarray(pinned_positions, dtype=np.float64).copy()
    return sim


def load_sequence(folder) -> dict:
    """Every complete chunk of a sequence folder, concatenated: positions (F, V, 3) float32, rotvecs (F, B, 3),
    root_translation (F, 3), root_velocity (F, 3), cloth_speed (F,), body_speed (F,), frames (F,)."""
    folder = Path(folder)
    files = sorted(folder.glob("chunk_*.npz"))
    if not files:
        raise FileNotFoundError(f"{folder}: no chunks")
    fields = ("frames", "positions", "rotvecs", "root_translation", "root_velocity", "cloth_speed", "body_speed")
    parts: dict = {name: [] for name in fields}
    for file in files:
        with np.load(file) as data:
            for name in fields:
                parts[name].append(data[name])
    return {name: np.concatenate(values) for name, values in parts.items()}
