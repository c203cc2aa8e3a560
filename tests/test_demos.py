"""Demonstration datasets: the HDF5 format, sampling, atomic writes, recording scripted
episodes, hindsight relabelling, robomimic import and the ``lcrl demos`` commands."""

from __future__ import annotations

import dataclasses
import json
import os
from collections import Counter

import h5py
import numpy as np
import pytest
from helpers import cli, error_line

from captioner.rule import RuleCaptioner
from captioner.splits import make_split
from lcrl.demos import (
    FORMAT,
    GIVEN,
    HINDSIGHT,
    VERSION,
    DemoDataset,
    DemoWriter,
    append_segments,
    import_robomimic,
)
from lcrl.errors import LcrlError
from train.configs.presets import PRESETS
from train.training.demos import (
    EPISODE_SCENE,
    RecordConfig,
    record,
    relabel,
    scene_arrays,
    scenes_from_arrays,
)

# --------------------------------------------------------------------------- helpers


def _episodes(n: int, seed: int = 0, discrete: bool = False, image: bool = True) -> list[dict]:
    """Random episodes of 3-12 steps with two given segments each (distinct texts)."""
    rng = np.random.default_rng(seed)
    out = []
    for e in range(n):
        t = int(rng.integers(3, 13))
        obs = {"observation": rng.normal(size=(t + 1, 5)).astype(np.float32)}
        if image:
            obs["image"] = rng.integers(0, 256, (t + 1, 6, 6, 3), dtype=np.uint8)
        if discrete:
            actions = rng.integers(0, 5, t)
        else:
            actions = rng.uniform(-1, 1, (t, 2)).astype(np.float32)
        mid = int(rng.integers(1, t))
        out.append(
            {
                "obs": obs,
                "actions": actions,
                "instruction": f"reach thing {e % 4}",
                "segments": [(mid, t, f"push thing {e % 3}")],
                "scene": {
                    "positions": rng.normal(size=(t + 1, 3, 3)),
                    "kinds": np.asarray(["red cube", "blue cylinder", ""]),
                    "height": np.asarray(0.8),
                },
                "success": bool(e % 3),
                "source": "test",
            }
        )
    return out


def _write(path, episodes, meta=None) -> None:
    with DemoWriter(
        path, meta or {"env": {"kind": "test"}}, episode_scene=("kinds", "height")
    ) as w:
        for ep in episodes:
            w.add_episode(**ep)


def _all_rows(data: DemoDataset, hindsight: bool = True) -> Counter:
    """Every (episode, step, goal, segment start) row of the segments, with multiplicity."""
    rows: Counter = Counter()
    for e, start, end, iid, _ in data.segments(hindsight).tolist():
        for t in range(start, end):
            rows[(e, t, iid, start)] += 1
    return rows


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    path = tmp_path_factory.mktemp("demos") / "small.h5"
    episodes = _episodes(12)
    _write(path, episodes, {"env": {"kind": "test"}, "note": [1, 2]})
    return path, episodes


# --------------------------------------------------------------------------- format


def test_round_trip(small):
    path, episodes = small
    with DemoDataset(path) as data:
        assert data.num_episodes == 12
        assert data.num_steps == sum(len(ep["actions"]) for ep in episodes)
        assert data.obs_shapes == {"observation": (5,), "image": (6, 6, 3)}
        assert data.action_shape == (2,) and not data.discrete
        assert data.meta == {"env": {"kind": "test"}, "note": [1, 2]}
        assert data.scene_keys == {"positions": False, "kinds": True, "height": True}
        seg = data.segments()
        for e, ep in enumerate(episodes):
            got = data.episode(e)
            for k, v in ep["obs"].items():
                np.testing.assert_array_equal(got["obs"][k], v)
                assert got["obs"][k].dtype == v.dtype
            np.testing.assert_array_equal(got["action"], ep["actions"])
            np.testing.assert_array_equal(got["scene"]["positions"], ep["scene"]["positions"])
            assert got["scene"]["kinds"].tolist() == ["red cube", "blue cylinder", ""]
            assert float(got["scene"]["height"]) == 0.8
            assert got["success"] == ep["success"] and got["source"] == "test"
            assert got["instruction"] == ep["instruction"]
            t = len(ep["actions"])
            rows = {
                (int(s), int(end), data.instructions[int(i)], int(o))
                for _, s, end, i, o in seg[seg[:, 0] == e]
            }
            (mid, end, text) = ep["segments"][0]
            want = {(mid, end, text, GIVEN)}
            if ep["success"]:  # a failed episode keeps its instruction but no segment for it
                want.add((0, t, ep["instruction"], GIVEN))
            assert rows == want
            np.testing.assert_array_equal(got["segments"], seg[seg[:, 0] == e])
        # ids index the table; the table holds each text once
        assert len(set(data.instructions)) == len(data.instructions)
        assert sorted(data.instructions) == sorted(
            {ep["instruction"] for ep in episodes} | {ep["segments"][0][2] for ep in episodes}
        )
        c = data.counts()
        assert c["segments"] == {"given": len(seg), "hindsight": 0}
        assert c["failures"] == 4 and c["successes"] == 8
        assert sum(r["given"] for r in c["per_instruction"].values()) == len(seg)
        assert "12 episodes" in data.summary()
        # images are chunked frame by frame and compressed
        with h5py.File(path) as f:
            assert f["obs/image"].chunks == (1, 6, 6, 3)
            assert f["obs/image"].compression == "lzf"


def test_discrete_actions_round_trip(tmp_path):
    episodes = _episodes(3, discrete=True, image=False)
    _write(tmp_path / "d.h5", episodes)
    with DemoDataset(tmp_path / "d.h5") as data:
        assert data.discrete and data.action_shape == ()
        np.testing.assert_array_equal(data.episode(1)["action"], episodes[1]["actions"])
        b = next(data.batches(8, ["observation"]))
        assert b.action.dtype == np.int64 and b.action.shape == (8,)


def test_batches_rows_lie_inside_segments(small):
    path, episodes = small
    with DemoDataset(path) as data:
        rows = _all_rows(data)
        seg_start = {(e, t, i): s for (e, t, i, s) in rows}  # goals are distinct per episode
        it = data.batches(7, ["observation", "initial", "image"], seed=3)
        for _ in range(30):
            b = next(it)
            assert b.obs["observation"].dtype == np.float32 and b.obs["image"].dtype == np.uint8
            assert b.action.shape == (7, 2) and b.action.dtype == np.float32
            for r in range(7):
                e, t, g = int(b.episode[r]), int(b.step[r]), int(b.goal[r])
                assert (e, t, g) in seg_start
                ep = episodes[e]
                np.testing.assert_array_equal(b.obs["observation"][r], ep["obs"]["observation"][t])
                np.testing.assert_array_equal(b.obs["image"][r], ep["obs"]["image"][t])
                np.testing.assert_array_equal(b.action[r], ep["actions"][t])
                start = seg_start[(e, t, g)]
                np.testing.assert_array_equal(b.obs["initial"][r], ep["obs"]["observation"][start])


def test_batches_are_deterministic_per_seed(small):
    path, _ = small
    with DemoDataset(path) as data:

        def first(seed, n=5):
            it = data.batches(16, ["observation"], seed=seed, cache_steps=30)
            return [next(it) for _ in range(n)]

        a, b, c = first(0), first(0), first(1)
        for x, y in zip(a, b, strict=True):
            np.testing.assert_array_equal(x.episode, y.episode)
            np.testing.assert_array_equal(x.step, y.step)
            np.testing.assert_array_equal(x.obs["observation"], y.obs["observation"])
        assert any(not np.array_equal(x.step, z.step) for x, z in zip(a, c, strict=True))


@pytest.mark.parametrize("cache_steps", [1, 25, 10_000])
def test_each_pass_serves_every_row_once_with_bounded_memory(small, cache_steps):
    path, _ = small
    with DemoDataset(path) as data:
        rows = _all_rows(data)
        total = sum(rows.values())
        batch = 9
        it = data.batches(batch, ["observation", "initial"], seed=5, cache_steps=cache_steps)
        starts = data.episode_start
        served: list[tuple[int, int, int, int]] = []
        while len(served) < 2 * total:
            b = next(it)
            for r in range(batch):
                e, t = int(b.episode[r]), int(b.step[r])
                # the initial observation names the segment start
                ep_obs = data.read_obs("observation", e)
                start = next(
                    s
                    for s in range(t + 1)
                    if np.array_equal(ep_obs[s], b.obs["initial"][r])
                    and (e, t, int(b.goal[r]), s) in rows
                )
                served.append((e, t, int(b.goal[r]), start))
        # the first pass is a permutation of every segment row, and so is the second
        assert Counter(served[:total]) == rows
        assert Counter(served[total : 2 * total]) == rows
        longest = int(np.max(np.diff(starts)))
        assert 0 < data.cache_high_water <= max(cache_steps, longest)


def test_given_only_batches_skip_hindsight(tmp_path, small):
    path, _ = small
    out = append_segments(
        path, [(0, 0, 2, "lift thing"), (1, 1, 3, "lift thing")], tmp_path / "h.h5"
    )
    with DemoDataset(out) as data:
        lift = data.instructions.index("lift thing")
        assert data.counts()["segments"]["hindsight"] == 2
        it = data.batches(32, ["observation"], hindsight=False)
        goals = np.concatenate([next(it).goal for _ in range(20)])
        assert lift not in goals
        it = data.batches(32, ["observation"], hindsight=True)
        goals = np.concatenate([next(it).goal for _ in range(20)])
        assert lift in goals


def test_append_segments_is_atomic_and_skips_duplicates(tmp_path, small):
    path, _ = small
    copy = tmp_path / "c.h5"
    copy.write_bytes(path.read_bytes())
    before = copy.read_bytes()
    with pytest.raises(LcrlError, match="outside the episode"):
        append_segments(copy, [(0, 0, 1, "ok"), (0, 5, 99, "too long")])
    assert copy.read_bytes() == before  # untouched
    assert not list(tmp_path.glob("*.part"))
    out = append_segments(copy, [(0, 0, 1, "new one"), (0, 0, 1, "new one")], meta={"x": 1})
    assert out == copy
    with DemoDataset(copy) as data:
        seg = data.segments()
        new = seg[seg[:, 4] == HINDSIGHT]
        assert len(new) == 1 and data.instructions[new[0, 3]] == "new one"
        assert data.meta["x"] == 1 and data.meta["env"] == {"kind": "test"}
    # a fresh relabelling replaces the hindsight rows
    append_segments(copy, [(2, 0, 1, "other")], drop_hindsight=True)
    with DemoDataset(copy) as data:
        seg = data.segments()
        assert [data.instructions[i] for i in seg[seg[:, 4] == HINDSIGHT, 3]] == ["other"]


def test_an_exception_mid_write_leaves_no_file(tmp_path):
    dest = tmp_path / "x.h5"
    episodes = _episodes(3)
    with pytest.raises(RuntimeError), DemoWriter(dest, episode_scene=("kinds", "height")) as w:
        w.add_episode(**episodes[0])
        w.add_episode(**episodes[1])
        raise RuntimeError("stop")
    assert not dest.exists() and not list(tmp_path.iterdir())
    # an existing file survives a failed rewrite unchanged
    _write(dest, episodes)
    before = dest.read_bytes()
    with pytest.raises(KeyboardInterrupt), DemoWriter(dest, episode_scene=("kinds", "height")) as w:
        w.add_episode(**episodes[2])
        raise KeyboardInterrupt
    assert dest.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["x.h5"]


def test_writer_and_reader_errors(tmp_path):
    with pytest.raises(LcrlError, match="no demonstration dataset"):
        DemoDataset(tmp_path / "missing.h5")
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(LcrlError, match="not an HDF5 file"):
        DemoDataset(tmp_path / "text.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "lcrl-caption-dataset"
    with pytest.raises(LcrlError, match="not an lcrl-demos dataset"):
        DemoDataset(tmp_path / "other.h5")
    ep = _episodes(1)[0]
    _write(tmp_path / "v.h5", [ep])
    with h5py.File(tmp_path / "v.h5", "r+") as f:
        assert f.attrs["format"] == FORMAT
        f.attrs["version"] = VERSION + 1
    with pytest.raises(LcrlError, match="version"):
        DemoDataset(tmp_path / "v.h5")
    w = DemoWriter(tmp_path / "w.h5", episode_scene=("kinds", "height"))
    with pytest.raises(LcrlError, match="policy units"):
        w.add_episode(**{**ep, "actions": ep["actions"] * 3})
    with pytest.raises(LcrlError, match="observations"):
        w.add_episode(**{**ep, "actions": ep["actions"][:-1]})
    with pytest.raises(LcrlError, match="outside the episode"):
        w.add_episode(**{**ep, "segments": [(0, 99, "x")]})
    with pytest.raises(LcrlError, match="episode_scene"):
        w.add_episode(**{**ep, "scene": {"kinds": ep["scene"]["kinds"], "odd": np.zeros(2)}})
    w.add_episode(**ep)
    with pytest.raises(LcrlError, match="observation keys"):
        w.add_episode(**{**ep, "obs": {"observation": ep["obs"]["observation"]}})
    w.close()
    with DemoDataset(tmp_path / "w.h5") as data:
        assert data.num_episodes == 1
        with pytest.raises(LcrlError, match="stores the observation keys"):
            data.batches(4, ["proprio"])
    empty = tmp_path / "e.h5"
    with DemoWriter(empty) as w2:  # an episode without an instruction has no segment
        w2.add_episode({"observation": np.zeros((3, 2))}, np.zeros((2, 1)))
    with DemoDataset(empty) as data, pytest.raises(LcrlError, match="no given segments"):
        data.batches(4, ["observation"], hindsight=False)
    with pytest.raises(LcrlError, match="nothing written"):
        DemoWriter(tmp_path / "none.h5").close()
    assert not (tmp_path / "none.h5").exists()


# --------------------------------------------------------------------------- recording


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """24 noisy lang2d episodes of reach, push and put (a few fail), relabelled."""
    folder = tmp_path_factory.mktemp("rec")
    cfg = RecordConfig(
        out=str(folder / "rec.h5"),
        families=("reach", "push", "put"),
        episodes=24,
        noise=0.6,
        seed=1,
        progress=False,
    )
    path = record(cfg)
    out = folder / "relabelled.h5"
    counts = relabel(path, out, starts_every=6, progress=False)
    return cfg, path, out, counts


def test_recorded_file_holds_what_the_policy_sees(recorded):
    cfg, path, _, _ = recorded
    env = dataclasses.replace(PRESETS["lang2d"][1].env, families=("reach", "push", "put"))
    with DemoDataset(path) as data:
        assert data.meta["env"] == json.loads(json.dumps(dataclasses.asdict(env)))
        assert data.meta["preset"] == "lang2d" and data.meta["split_seed"] == 0
        assert data.meta["recording"]["noise"] == cfg.noise == 0.6
        assert data.obs_shapes == {"observation": (58,)}  # the lang2d preset's observation
        assert data.action_shape == (2,)
        assert set(data.scene_keys) >= {"positions", "gripper", *EPISODE_SCENE}
        assert data.num_episodes == 24
        c = data.counts()
        assert c["failures"] >= 1  # noisy put fails sometimes; failures are kept
        rule = RuleCaptioner(("reach", "push", "put"))
        for e in range(data.num_episodes):
            ep = data.episode(e)
            scenes = scenes_from_arrays(ep["scene"])
            assert len(scenes) == ep["length"] + 1 == len(ep["obs"]["observation"])
            # the pusher position leads the observation
            np.testing.assert_allclose(
                ep["obs"]["observation"][:, :2], [s.gripper[:2] for s in scenes], atol=1e-6
            )
            assert np.all(np.abs(ep["action"]) <= 1.0)
            text = ep["instruction"]
            holds = rule.satisfied(text, scenes[0], scenes[-1])
            assert holds == ep["success"]
            given = ep["segments"][ep["segments"][:, 4] == GIVEN]
            if ep["success"]:  # one given segment ending at the success step
                assert given.tolist() == [[e, 0, ep["length"], data.instructions.index(text), 0]]
                assert not any(rule.satisfied(text, scenes[0], s) for s in scenes[:-1])
            else:
                assert len(given) == 0 and ep["length"] == 50


def test_scene_arrays_round_trip():
    from envs.tabletop2d import Tabletop2DEnv

    env = Tabletop2DEnv(num_objects=3)
    env.reset(seed=4)
    scenes = [env.scene()]
    for _ in range(3):
        env.step(np.array([0.7, -0.2], np.float32))
        scenes.append(env.scene())
    back = scenes_from_arrays(scene_arrays(scenes))
    for a, b in zip(scenes, back, strict=True):
        assert a.names == b.names
        np.testing.assert_array_equal(a.positions, b.positions)
        np.testing.assert_array_equal(a.gripper, b.gripper)
        np.testing.assert_array_equal(a.touching, b.touching)
        assert a.table_bounds == b.table_bounds


def test_relabelled_segments_end_where_the_instruction_first_holds(recorded):
    _, path, out, counts = recorded
    rule = RuleCaptioner(("reach", "push", "put"))
    with DemoDataset(out) as data, DemoDataset(path) as before:
        seg = data.segments()
        hind = seg[seg[:, 4] == HINDSIGHT]
        assert len(hind) == counts["hindsight_segments"] > 0
        np.testing.assert_array_equal(seg[seg[:, 4] == GIVEN], before.segments())
        assert {r[1] for r in hind.tolist()} > {0}  # starts every 6 steps too
        scenes = {}
        for e, start, end, iid, _ in hind.tolist():
            if e not in scenes:
                scenes[e] = scenes_from_arrays(data.episode(e)["scene"])
            s = scenes[e]
            text = data.instructions[iid]
            assert start < end
            assert rule.satisfied(text, s[start], s[end])
            assert not any(rule.satisfied(text, s[start], s[k]) for k in range(start, end))
        # the given segments are not repeated as hindsight ones
        assert not {tuple(r[:4]) for r in hind.tolist()} & {
            tuple(r[:4]) for r in seg[seg[:, 4] == GIVEN].tolist()
        }
        failed = np.flatnonzero(data.episode_success == 0)
        gained = {int(e) for e in hind[:, 0]}
        assert counts["failed_episodes"] == len(failed)
        assert counts["failed_with_hindsight"] == len(gained & set(failed.tolist())) >= 1
        assert counts["given_segments"] + counts["hindsight_segments"] == len(seg)
        assert counts["instructions_after"] >= counts["instructions_before"]
        fam = counts["per_family"]
        assert sum(r["hindsight"] for r in fam.values()) == len(hind)
        assert set(fam) <= {"reach", "push", "put"}
        assert counts["segments_per_episode"] == pytest.approx(len(seg) / 24)
        # sampling from the relabelled file feeds a language policy's observation keys
        b = next(data.batches(64, ["observation", "initial"], seed=0))
        assert b.obs["initial"].shape == (64, 58) and b.goal.max() < len(data.instructions)


def test_train_only_never_adds_heldout_instructions(recorded, tmp_path):
    _, path, out, _ = recorded
    split = make_split(0, ("reach", "push", "put"))
    heldout, train = set(split.heldout), set(split.train)
    with DemoDataset(out) as data:
        texts = {data.instructions[i] for i in data.segments()[:, 3]}
        assert texts <= train and not texts & heldout
    counts = relabel(path, tmp_path / "all.h5", starts_every=6, train_only=False, progress=False)
    with DemoDataset(tmp_path / "all.h5") as data:
        texts = {data.instructions[i] for i in data.segments()[:, 3]}
    # without the filter held-out combinations do appear (so the filter above was tested)
    assert texts & heldout
    assert counts["hindsight_segments"] > 0


def test_relabel_errors(recorded, tmp_path, small):
    _, path, out, _ = recorded
    with pytest.raises(LcrlError, match="exists"):
        relabel(path, out, progress=False)
    with pytest.raises(LcrlError, match="camera frames"):
        relabel(path, tmp_path / "x.h5", captioner=str(tmp_path), progress=False)
    with pytest.raises(LcrlError, match="which tabletop"):
        relabel(small[0], tmp_path / "y.h5", progress=False)
    with pytest.raises(LcrlError, match="starts-every"):
        relabel(path, tmp_path / "z.h5", starts_every=-1, progress=False)
    with pytest.raises(LcrlError, match="preset"):
        record(RecordConfig(out=str(tmp_path / "s.h5"), preset="state2d", episodes=1))
    with pytest.raises(LcrlError, match="families"):
        record(RecordConfig(out=str(tmp_path / "s.h5"), families=("lift",), episodes=1))


def test_relabel_in_place_is_atomic(recorded, tmp_path):
    _, path, _, _ = recorded
    copy = tmp_path / "c.h5"
    copy.write_bytes(path.read_bytes())
    counts = relabel(copy, copy, progress=False)
    again = relabel(copy, copy, progress=False)  # replaces its own hindsight rows
    assert again["hindsight_segments"] == counts["hindsight_segments"] > 0
    assert [p.name for p in tmp_path.iterdir()] == ["c.h5"]


class _FakeModels:
    """Stands in for a learned captioner: says "reach the red cube" once the frame has
    changed enough from the first one."""

    captioner = object()
    reward = None
    frame_shape = (32, 32, 3)

    def has(self, model: str) -> bool:  # a captioner without a reward model
        return model == "captioner"

    proprio_dim = 2
    text = "reach the red cube"

    @staticmethod
    def changed(first: np.ndarray, current: np.ndarray) -> bool:
        return float(np.abs(current.astype(float) - first.astype(float)).mean()) > 1.0

    def captions(self, first, current, p0, p, beam=0):
        assert p0.shape == p.shape == (len(first), 2)
        return [
            [(self.text if self.changed(a, b) else "<none>", -0.1)]
            for a, b in zip(first, current, strict=True)
        ]


def test_learned_captioner_relabels_from_frames(tmp_path, monkeypatch):
    from captioner import learned

    path = record(
        RecordConfig(
            out=str(tmp_path / "img.h5"), episodes=4, images=True, image_size=32, progress=False
        )
    )
    fake = _FakeModels()
    monkeypatch.setattr(learned.LearnedCaptioner, "load", classmethod(lambda cls, p, device: fake))
    counts = relabel(
        path, tmp_path / "out.h5", captioner=str(tmp_path), starts_every=10, progress=False
    )
    assert counts["captioner"] == str(tmp_path)
    with DemoDataset(tmp_path / "out.h5") as data:
        hind = data.segments()[data.segments()[:, 4] == HINDSIGHT]
        want = []
        for e in range(data.num_episodes):
            frames = data.read_obs("image", e)
            for start in range(0, len(frames) - 1, 10):
                hits = [
                    k
                    for k in range(start + 1, len(frames))
                    if fake.changed(frames[start], frames[k])
                ]
                if hits:
                    want.append((e, start, hits[0]))
        assert want  # the frames do change
        got = [(e, s, t) for e, s, t, i, _ in hind.tolist() if data.instructions[i] == fake.text]
        given = {
            (e, s, t)
            for e, s, t, i, _ in data.segments(hindsight=False).tolist()
            if data.instructions[i] == fake.text
        }
        assert sorted(got) == sorted(w for w in want if w not in given)


def test_learned_captioner_needs_frames_of_its_size(tmp_path, monkeypatch):
    from captioner import learned

    path = record(
        RecordConfig(
            out=str(tmp_path / "img.h5"), episodes=1, images=True, image_size=24, progress=False
        )
    )
    monkeypatch.setattr(
        learned.LearnedCaptioner, "load", classmethod(lambda cls, p, device: _FakeModels())
    )
    with pytest.raises(LcrlError, match="32x32x3 frames"):
        relabel(path, tmp_path / "o.h5", captioner=str(tmp_path), progress=False)


# --------------------------------------------------------------------------- robomimic


def _robomimic_file(path, problem_info: dict | None = None, lengths=(5, 7, 4)) -> dict:
    rng = np.random.default_rng(0)
    demos = {}
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["env_args"] = json.dumps({"env_name": "Lift", "type": 1})
        if problem_info is not None:
            data.attrs["problem_info"] = json.dumps(problem_info)
        for i, t in enumerate(lengths):
            g = data.create_group(f"demo_{i}")
            obs = {
                "robot0_eef_pos": rng.normal(size=(t + 1, 3)),
                "object": rng.normal(size=(t + 1, 4)),
                "robot0_gripper_qpos": rng.normal(size=(t + 1, 2)),
                "agentview_image": rng.integers(0, 256, (t + 1, 8, 8, 3), dtype=np.uint8),
            }
            for k, v in obs.items():
                g.create_dataset(f"obs/{k}", data=v[:-1])
                g.create_dataset(f"next_obs/{k}", data=v[1:])
            actions = rng.uniform(-1.2, 1.2, (t, 7))
            g.create_dataset("actions", data=actions)
            g.create_dataset("rewards", data=np.zeros(t))
            demos[i] = (obs, actions)
        # demo_10 sorts after demo_2 (numeric order)
    return demos


def test_import_robomimic(tmp_path):
    src = tmp_path / "rm.h5"
    demos = _robomimic_file(src, {"language_instruction": "pick up the  black bowl"})
    with pytest.warns(UserWarning, match="clipped"):
        out = import_robomimic(src, tmp_path / "d.h5", obs_keys=("robot0_eef_pos", "object"))
    with DemoDataset(out) as data:
        assert data.num_episodes == 3 and data.instructions == ["pick up the black bowl"]
        assert data.obs_shapes == {"observation": (7,), "image": (8, 8, 3)}
        assert data.meta["robomimic_env_args"]["env_name"] == "Lift"
        clipped = sum(int((np.abs(a) > 1).sum()) for _, a in demos.values())
        assert data.meta["import"]["clipped_values"] == clipped > 0
        for e, (obs, actions) in demos.items():
            ep = data.episode(e)
            want = np.concatenate([obs["robot0_eef_pos"], obs["object"]], 1).astype(np.float32)
            np.testing.assert_array_equal(ep["obs"]["observation"], want)
            np.testing.assert_array_equal(ep["obs"]["image"], obs["agentview_image"])
            np.testing.assert_array_equal(ep["action"], np.clip(actions, -1, 1).astype(np.float32))
            assert ep["segments"].tolist() == [[e, 0, len(actions), 0, GIVEN]]
            assert ep["success"] is None and ep["source"] == "robomimic"
    # the argument wins over problem_info; default keys: every low-dim key, sorted
    with pytest.warns(UserWarning, match="clipped"):
        out = import_robomimic(src, tmp_path / "e.h5", instruction="lift the cube", image_key=None)
    with DemoDataset(out) as data:
        assert data.instructions == ["lift the cube"]
        assert data.obs_shapes == {"observation": (9,)}
        np.testing.assert_array_equal(
            data.episode(0)["obs"]["observation"][:, :4], demos[0][0]["object"].astype(np.float32)
        )


def test_import_robomimic_errors(tmp_path):
    src = tmp_path / "rm.h5"
    _robomimic_file(src)
    with pytest.raises(LcrlError, match="--instruction"):
        import_robomimic(src, tmp_path / "d.h5")
    with pytest.raises(LcrlError, match="no observation keys"):
        import_robomimic(src, tmp_path / "d.h5", instruction="x", obs_keys=("nope",))
    with pytest.raises(LcrlError, match="no robomimic file"):
        import_robomimic(tmp_path / "missing.h5", tmp_path / "d.h5", instruction="x")
    with h5py.File(tmp_path / "bad.h5", "w") as f:
        f.create_group("other")
    with pytest.raises(LcrlError, match="'data' group"):
        import_robomimic(tmp_path / "bad.h5", tmp_path / "d.h5", instruction="x")
    assert not (tmp_path / "d.h5").exists()


# --------------------------------------------------------------------------- CLI


def test_cli_record_relabel_info(tmp_path, capsys):
    raw, out = tmp_path / "raw.h5", tmp_path / "rel.h5"
    code = cli(
        "demos",
        "record",
        "--out",
        str(raw),
        "--episodes",
        "6",
        "--families",
        "reach",
        "push",
        "--no-progress",
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "scripted success per family" in text and "reach" in text
    assert "saved 6 episodes" in text and raw.exists()
    code = cli(
        "demos",
        "relabel",
        str(raw),
        "--out",
        str(out),
        "--json",
        str(tmp_path / "c.json"),
        "--no-progress",
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "segments:" in text and "per family" in text and "distinct instructions" in text
    counts = json.loads((tmp_path / "c.json").read_text())
    assert counts["episodes"] == 6 and counts["out"] == str(out)
    assert cli("demos", "info", str(out), "--instructions") == 0
    text = capsys.readouterr().out
    assert "6 episodes" in text and "segments per family" in text and "preset lang2d" in text
    assert cli("demos", "info", str(out), "--json") == 0
    info = json.loads(capsys.readouterr().out)
    assert info["episodes"] == 6 and info["segments"]["given"] >= 1
    # mistakes: one line, status 2
    assert cli("demos", "relabel", str(raw)) == 2
    assert "pass --out" in error_line(capsys.readouterr().err)
    assert cli("demos", "info", str(tmp_path / "missing.h5")) == 2
    assert error_line(capsys.readouterr().err).startswith("lcrl: error: no demonstration dataset")
    assert cli("demos", "record", "--out", str(raw), "--episodes", "1", "--no-progress") == 2
    assert "--overwrite" in error_line(capsys.readouterr().err)


def test_cli_import_robomimic(tmp_path, capsys):
    src = tmp_path / "rm.h5"
    _robomimic_file(src, {"language_instruction": "open the drawer"})
    code = cli(
        "demos",
        "import-robomimic",
        str(src),
        "--out",
        str(tmp_path / "d.h5"),
        "--obs-keys",
        "object",
        "--no-progress",
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "3 episodes" in text and "observation = object" in text and "clipped" in text
    code = cli(
        "demos",
        "import-robomimic",
        str(src),
        "--out",
        str(tmp_path / "e.h5"),
        "--instruction",
        "open it",
        "--image-key",
        "none",
        "--no-progress",
    )
    assert code == 0
    with DemoDataset(tmp_path / "e.h5") as data:
        assert data.instructions == ["open it"] and "image" not in data.obs_shapes
    capsys.readouterr()
    assert cli("demos", "import-robomimic", str(src), "--out", str(tmp_path / "d.h5")) == 2
    assert "exists" in error_line(capsys.readouterr().err)


def test_ctrl_c_keeps_the_finished_episodes(tmp_path, monkeypatch, capsys):
    """Interrupting a recording completes the file with the episodes finished so far."""
    import train.training.demo_recording as demos  # where episodes are recorded

    real = demos._record_episode
    calls = {"n": 0}

    def interrupted(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(demos, "_record_episode", interrupted)
    out = tmp_path / "i.h5"
    with pytest.raises(KeyboardInterrupt):
        record(RecordConfig(out=str(out), episodes=10, progress=False))
    assert "kept the 3 finished episodes" in capsys.readouterr().out
    with DemoDataset(out) as data:
        assert data.num_episodes == 3 and data.meta["interrupted"]
    calls["n"] = 3
    with pytest.raises(KeyboardInterrupt):
        record(RecordConfig(out=str(tmp_path / "j.h5"), episodes=10, progress=False))
    assert "nothing written" in capsys.readouterr().out
    assert sorted(p.name for p in tmp_path.iterdir()) == ["i.h5"]
    assert os.path.getsize(out) > 0


@pytest.mark.slow
def test_robosuite_recording(tmp_path):
    out = tmp_path / "rs.h5"
    path = record(RecordConfig(out=str(out), preset="robosuite", episodes=2, progress=False))
    with DemoDataset(path) as data:
        assert data.num_episodes == 2 and data.action_shape == (4,)
        assert data.meta["env"]["kind"] == "robosuite"
        assert {"grasped", "touching", "positions"} <= set(data.scene_keys)
        rule = RuleCaptioner(("reach", "push"))
        for e in range(2):
            ep = data.episode(e)
            scenes = scenes_from_arrays(ep["scene"])
            assert scenes[0].table_height > 0.5  # the robosuite table, not the 2D one
            assert rule.satisfied(ep["instruction"], scenes[0], scenes[-1]) == ep["success"]
    counts = relabel(path, tmp_path / "rel.h5", progress=False)
    assert counts["episodes"] == 2
