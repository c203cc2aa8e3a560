"""Importing robomimic and LIBERO files as demonstration files."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from lcrl.demos.writer import DemoWriter
from lcrl.errors import LcrlError


def _demo_names(group: Any) -> list[str]:
    def key(name: str) -> tuple[int, str]:
        tail = name.rsplit("_", 1)[-1]
        return (int(tail), name) if tail.isdigit() else (1 << 62, name)

    return sorted((n for n in group if n.startswith("demo")), key=key)


def _instruction_from(attrs: Any) -> str | None:
    raw = attrs.get("problem_info")
    if raw is None:
        return None
    if isinstance(raw, bytes):
        raw = raw.decode()
    try:
        info = json.loads(raw)
    except (TypeError, json.JSONDecodeError):
        return None
    text = info.get("language_instruction") if isinstance(info, dict) else None
    if isinstance(text, (list, tuple)):
        text = " ".join(str(t) for t in text)
    if not isinstance(text, str) or not text.strip():
        return None
    return " ".join(text.split())


def _attr_json(attrs: Any, name: str) -> Any:
    raw = attrs.get(name)
    if raw is None:
        return None
    if isinstance(raw, bytes):
        raw = raw.decode()
    try:
        return json.loads(raw)
    except (TypeError, json.JSONDecodeError):
        return str(raw)


def import_robomimic(
    src: str | os.PathLike,
    dst: str | os.PathLike,
    instruction: str | None = None,
    obs_keys: Sequence[str] | None = None,
    image_key: str | None = "auto",
    proprio_keys: Sequence[str] = (),
    overwrite: bool = False,
    progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None,
) -> Path:
    """Convert a robomimic-style HDF5 file (robomimic, LIBERO) into a demonstration dataset.

    The source holds ``data/demo_<i>/{obs/<key>, actions, next_obs/<key>, ...}``;
    ``data.attrs["env_args"]`` (JSON) is kept in the meta, and LIBERO's
    ``data.attrs["problem_info"]`` (JSON) may carry the ``"language_instruction"``.
    Each demo becomes one episode whose whole length is one given segment (outcome
    unknown). Its ``T`` observations are completed by the last ``next_obs`` row; without
    ``next_obs`` the last action is dropped instead.

    Args:
        src: the robomimic file.
        dst: the demonstration dataset to write.
        instruction: the instruction of every demo (default: ``problem_info``'s
            ``language_instruction``).
        obs_keys: low-dimensional observation keys concatenated, in this order, into
            ``observation`` (default: every non-image key of the first demo, sorted).
        image_key: the camera key stored as ``image`` (``"auto"``: ``agentview_image``,
            ``agentview_rgb`` or the first image key; None or ``""``: no image).
        proprio_keys: keys concatenated into ``proprio`` (the robot's own state for
            camera policies; none by default).
        overwrite: replace an existing ``dst``.
        progress: wraps the iteration over demos (e.g. ``tqdm``).

    Returns:
        The path written. ``meta["import"]["clipped_values"]`` counts action values that
        were outside ``[-1, 1]`` and were clipped (a warning is printed too).

    Raises:
        LcrlError: missing or malformed source, no instruction, unknown keys.
    """
    import warnings

    src_path, dst_path = Path(src), Path(dst)
    if not src_path.is_file():
        raise LcrlError(f"no robomimic file at {src_path}")
    if dst_path.exists() and not overwrite:
        raise LcrlError(f"{dst_path} exists; pass --overwrite to replace it")
    try:
        f = h5py.File(src_path, "r")
    except OSError as e:
        raise LcrlError(f"{src_path} is not an HDF5 file ({e})") from None
    with f:
        if "data" not in f or not isinstance(f["data"], h5py.Group):
            raise LcrlError(f"{src_path} has no 'data' group: not a robomimic-style file")
        data = f["data"]
        demos = _demo_names(data)
        if not demos:
            raise LcrlError(f"{src_path} has no data/demo_<i> groups")
        text = instruction if instruction and instruction.strip() else None
        if text is None:
            text = _instruction_from(data.attrs)
        if text is None:
            raise LcrlError(
                f"{src_path} names no instruction (no language_instruction in "
                "data.attrs['problem_info']): pass --instruction TEXT"
            )
        text = " ".join(text.split())
        first = data[demos[0]]
        if "obs" not in first or "actions" not in first:
            raise LcrlError(f"{src_path}: {demos[0]} has no obs group or no actions")
        available = {k: first["obs"][k] for k in first["obs"]}

        def is_image(ds: Any) -> bool:
            return ds.dtype == np.uint8 and ds.ndim == 4

        if obs_keys is None:
            obs_keys = sorted(k for k, ds in available.items() if not is_image(ds))
        if image_key == "auto":
            images = sorted(k for k, ds in available.items() if is_image(ds))
            preferred = [k for k in ("agentview_image", "agentview_rgb") if k in images]
            image_key = (preferred or images or [None])[0]
        wanted = [*obs_keys, *proprio_keys, *([image_key] if image_key else [])]
        missing = [k for k in wanted if k not in available]
        if missing:
            raise LcrlError(
                f"{src_path} has no observation keys {missing}; it has {sorted(available)}"
            )
        if not obs_keys and not image_key:
            raise LcrlError("choose at least one observation key or an image key")
        env_args = _attr_json(data.attrs, "env_args")
        clipped = 0
        total = 0
        settings = {
            "source": str(src_path),
            "obs_keys": list(obs_keys),
            "image_key": image_key or None,
            "proprio_keys": list(proprio_keys),
            "demos": len(demos),
        }
        meta = {"env": None, "robomimic_env_args": env_args, "import": settings}
        writer = DemoWriter(dst_path, meta, instructions=[text], overwrite=overwrite)
        try:
            iterator = progress(demos) if progress is not None else demos
            for name in iterator:
                demo = data[name]
                actions = np.asarray(demo["actions"][:], np.float64)
                if actions.ndim == 1:
                    actions = actions[:, None]
                has_next = "next_obs" in demo

                def rows(key: str, demo: Any = demo, has_next: bool = has_next) -> np.ndarray:
                    v = np.asarray(demo["obs"][key][:])
                    if has_next and key in demo["next_obs"]:
                        return np.concatenate([v, np.asarray(demo["next_obs"][key][-1:])])
                    return v

                def vec(keys: Sequence[str], rows: Any = rows) -> np.ndarray:
                    parts = [rows(k) for k in keys]
                    n = min(len(p) for p in parts)
                    flat = [p[:n].reshape(n, -1).astype(np.float32) for p in parts]
                    return np.concatenate(flat, axis=1)

                obs: dict[str, np.ndarray] = {}
                if obs_keys:
                    obs["observation"] = vec(obs_keys)
                if proprio_keys:
                    obs["proprio"] = vec(proprio_keys)
                if image_key:
                    obs["image"] = rows(image_key).astype(np.uint8)
                n_obs = min(len(v) for v in obs.values())
                t = min(len(actions), n_obs - 1)
                if t < 1:
                    continue
                obs = {k: v[: t + 1] for k, v in obs.items()}
                actions = actions[:t]
                outside = np.abs(actions) > 1.0
                clipped += int(outside.sum())
                total += actions.size
                writer.add_episode(
                    obs,
                    np.clip(actions, -1.0, 1.0).astype(np.float32),
                    instruction=text,
                    source="robomimic",
                )
            settings["clipped_values"] = clipped
            settings["action_values"] = total
            writer.update_meta(meta)
            path = writer.close()
        except BaseException:
            writer.discard()
            raise
    if clipped:
        warnings.warn(
            f"{clipped} of {total} action values were outside [-1, 1] and were clipped",
            stacklevel=2,
        )
    return path
