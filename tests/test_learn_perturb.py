"""``cosim learn``'s collaboration as deployed (issue 49, docs/learnability.md): pose error, latency and lost
messages on synthetic learn records (no engine), their seeded draws, the bytes each fusion mode sends, and bad
values refused with one line."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from cosim.errors import InputError
from cosim.learn import samples as smp
from cosim.learn.samples import Perturb, Setup, make_item, quantise

HAVE_TORCH = importlib.util.find_spec("torch") is not None
TICK_NS = 100_000_000  # 10 Hz: a delay of 100 ms is one tick
EGO, COLLAB = "vehicle_0", "rsu_0"


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    pose[:2, 3] = [x, y]
    return pose


def _record(tick: int, collab_xy: tuple[float, float] = (20.0, 6.0), yaw: float = 0.4,
            delivery: float = 1.0, delay_ms: float = 10.0) -> dict:
    """A learn record of tick ``tick``: the ego at the map origin, the collaborator at ``collab_xy`` + (tick, 0)
    (it moves 1 m a tick) turned by ``yaw``, one car ahead at (30 + tick, -4) (labels move with it). The
    collaborator's points are a fixed pattern in its frame plus one point at (tick mod 50, 0, -1) that names
    the tick."""
    x, y = collab_xy[0] + tick, collab_xy[1]
    local = np.array([[5.0, 2.0, -1.0], [-3.0, 4.0, -0.5], [8.0, -6.0, -1.5], [float(tick % 50), 0.0, -1.0]])
    ego_pts = np.array([[12.0, 3.0, -1.0], [-7.0, -2.0, -1.2]])
    return {"tick": tick, "t_ns": tick * TICK_NS, "tick_ns": TICK_NS, "agents": [EGO, COLLAB],
            "map_from": np.stack([np.eye(4), _pose(x, y, yaw)]),
            "points": [quantise(ego_pts)[0], quantise(local)[0]],
            "intensity": [np.full(2, 50, np.uint8), np.full(4, 200, np.uint8)],
            "hits": [np.zeros((2, 0), np.int64), np.array([[9], [3]], np.int64)],
            "label_track_ids": np.array([9]), "label_classes": ["car"],
            "label_centers": np.array([[30.0 + tick, -4.0, -1.0]]),
            "label_rotations": np.array([[0.0, 0.0, 0.0, 1.0]]), "label_sizes": np.array([[4.4, 1.8, 1.5]]),
            "agent_tracks": {}, "links": {f"{COLLAB}>{EGO}": delivery, f"{EGO}>{COLLAB}": delivery},
            "link_delay_ms": {f"{COLLAB}>{EGO}": delay_ms, f"{EGO}>{COLLAB}": delay_ms}}


_record_at = _record


def _collab_cloud(item: dict) -> np.ndarray:
    """The collaborator's points of an early-fusion sample (after the ego's own, in the ego frame)."""
    return item["clouds"][0][2:, :3]


def _in_ego(rec: dict, pose: np.ndarray) -> np.ndarray:
    local = smp.dequantise(rec["points"][1], rec["intensity"][1])[:, :3].astype(np.float64)
    return local @ pose[:3, :3].T + pose[:3, 3]


# ---------------------------------------------------------------------------------------------- pose error

@pytest.mark.parametrize("error", [(0.5, -0.2, 0.0), (0.0, 0.0, math.radians(3.0)), (-0.3, 0.4, math.radians(-1.5))])
def test_a_known_pose_error_moves_a_collaborators_points_by_exactly_that_error(monkeypatch, error):
    dx, dy, dyaw = error
    rec = _record(0)
    clean = make_item(rec, EGO, Setup(fusion="early", agents="all"), "ep")
    monkeypatch.setattr(smp, "pose_error", lambda perturb, episode, tick, agent: error)
    noisy = make_item(rec, EGO, Setup(fusion="early", agents="all", perturb=Perturb(pose_m=0.1, pose_deg=0.1)), "ep")
    np.testing.assert_array_equal(noisy["clouds"][0][:2], clean["clouds"][0][:2])  # the ego's own: untouched
    centre = rec["map_from"][1][:2, 3]  # the collaborator's LiDAR: the error turns its points about it, then moves them
    c, s = math.cos(dyaw), math.sin(dyaw)
    rel = _collab_cloud(clean)[:, :2].astype(np.float64) - centre
    expected = np.stack([c * rel[:, 0] - s * rel[:, 1], s * rel[:, 0] + c * rel[:, 1]], axis=1) + centre + [dx, dy]
    np.testing.assert_allclose(_collab_cloud(noisy)[:, :2], expected, atol=2e-5)
    np.testing.assert_allclose(_collab_cloud(noisy)[:, 2], _collab_cloud(clean)[:, 2], atol=1e-6)
    if dyaw == 0.0:  # a pure shift: every point moves by (dx, dy)
        np.testing.assert_allclose(_collab_cloud(noisy)[:, :2] - _collab_cloud(clean)[:, :2],
                                   np.tile([dx, dy], (4, 1)), atol=2e-5)
    # intermediate fusion: the cloud stays in the collaborator's frame and the warp's pose carries the error
    inter = make_item(rec, EGO, Setup(fusion="intermediate", agents="all", perturb=Perturb(pose_m=0.1)), "ep")
    clean_inter = make_item(rec, EGO, Setup(fusion="intermediate", agents="all"), "ep")
    np.testing.assert_allclose(inter["poses"][1], clean_inter["poses"][1] + [dyaw, dx, dy], atol=1e-9)
    np.testing.assert_allclose(inter["clouds"][1], clean_inter["clouds"][1], atol=2e-5)
    np.testing.assert_array_equal(inter["poses"][0], clean_inter["poses"][0])
    assert len(noisy["targets"][0][0]) == 1  # labels are the ego's: never perturbed
    np.testing.assert_array_equal(noisy["targets"][0][0], clean["targets"][0][0])


def test_pose_errors_are_gaussian_with_the_given_deviations_and_seeded():
    perturb = Perturb(pose_m=0.4, pose_deg=0.6, seed=3)
    draws = np.array([smp.pose_error(perturb, "ep", t, COLLAB) for t in range(4000)])
    assert abs(draws[:, 0].std() - 0.4) < 0.4 * 0.05 and abs(draws[:, 1].std() - 0.4) < 0.4 * 0.05
    assert abs(np.degrees(draws[:, 2]).std() - 0.6) < 0.6 * 0.05
    assert np.abs(draws.mean(axis=0) / (np.array([0.4, 0.4, math.radians(0.6)]) / math.sqrt(4000))).max() < 4
    assert smp.pose_error(perturb, "ep", 7, COLLAB) == smp.pose_error(Perturb(pose_m=0.4, pose_deg=0.6, seed=3),
                                                                       "ep", 7, COLLAB)
    assert smp.pose_error(perturb, "ep", 7, COLLAB) != smp.pose_error(Perturb(pose_m=0.4, pose_deg=0.6, seed=4),
                                                                       "ep", 7, COLLAB)
    # each collaborator's error is its own, the same for every ego that receives its message
    assert smp.pose_error(perturb, "ep", 7, COLLAB) != smp.pose_error(perturb, "ep", 7, "drone_0")


def test_the_same_seed_gives_the_same_samples_and_another_seed_others():
    rec = _record(2)

    def item(seed: int) -> dict:
        return make_item(rec, EGO, Setup(fusion="early", agents="all",
                                         perturb=Perturb(pose_m=0.3, pose_deg=0.3, loss=0.0, seed=seed)), "ep")

    np.testing.assert_array_equal(item(5)["clouds"][0], item(5)["clouds"][0])
    assert not np.array_equal(item(5)["clouds"][0], item(6)["clouds"][0])
    clean = make_item(rec, EGO, Setup(fusion="early", agents="all"), "ep")
    seed_only = make_item(rec, EGO, Setup(fusion="early", agents="all", perturb=Perturb(seed=9)), "ep")
    assert clean["clouds"][0].tobytes() == seed_only["clouds"][0].tobytes()  # a seed alone perturbs nothing


# ---------------------------------------------------------------------------------------------- latency

def _history(records: dict[int, dict]):
    return lambda t: records.get(t)


@pytest.mark.parametrize("perturb, ticks", [(Perturb(latency_ms=100), 1), (Perturb(latency_ms=300), 3),
                                            (Perturb(latency_links=True), 2)])
def test_latency_takes_the_earlier_tick_with_the_pose_of_that_tick(perturb, ticks):
    records = {t: _record(t, delay_ms=130.0) for t in range(6)}  # a link delay of 130 ms: 2 ticks, rounded up
    now = records[5]
    item = make_item(now, EGO, Setup(fusion="early", agents="all", perturb=perturb), "ep", _history(records))
    then = records[5 - ticks]
    np.testing.assert_allclose(_collab_cloud(item), _in_ego(then, then["map_from"][1]), atol=2e-5)
    assert round(float(_collab_cloud(item)[3, 0] - then["map_from"][1][0, 3]), 3) == round(
        (5 - ticks) * math.cos(0.4), 3)  # the tick-naming point says which tick's data came
    np.testing.assert_allclose(item["targets"][0][0][:, :2], [[35.0, -4.0]])  # the labels: the ego's tick
    inter = make_item(now, EGO, Setup(fusion="intermediate", agents="all", perturb=perturb), "ep", _history(records))
    np.testing.assert_allclose(inter["poses"][1], [0.4, 20.0 + 5 - ticks, 6.0], atol=1e-9)  # its pose of then
    # before the episode had run that long, nothing of the collaborator has arrived
    early = make_item(records[ticks - 1], EGO, Setup(fusion="early", agents="all", perturb=perturb), "ep",
                      _history(records))
    assert early["sent"] == [] and len(early["clouds"][0]) == 2


def test_a_link_delay_rounds_up_to_whole_ticks():
    for delay_ms, ticks in ((0.0, 0), (1.0, 1), (100.0, 1), (100.5, 2), (250.0, 3)):
        assert smp.latency_ticks(Perturb(latency_links=True), _record(0, delay_ms=delay_ms), COLLAB, EGO) == ticks
    assert smp.latency_ticks(Perturb(latency_ms=200), _record(0), COLLAB, EGO) == 2
    with pytest.raises(InputError, match="latency links needs /comm/links"):
        smp.latency_ticks(Perturb(latency_links=True), {**_record(0), "link_delay_ms": None}, COLLAB, EGO)


class _Source:
    """The learn records of one synthetic episode, as :class:`cosim.learn.data.Samples` reads them."""

    def __init__(self, n_ticks: int, tick_ns: int = TICK_NS, every: int = 1, **kw):
        self.every = every
        self.records = {t: {**_record(t, **kw), "tick_ns": tick_ns, "t_ns": t * tick_ns} for t in range(n_ticks)}
        self.keys = [("ep", t, EGO) for t in range(0, n_ticks, every)]

    def record(self, episode: str, tick: int) -> dict:
        if tick not in self.records or tick % self.every:
            raise InputError(f"tick {tick} is not in the cache")
        return self.records[tick]

    def tick_ns(self, episode: str) -> int:
        return self.records[0]["tick_ns"]

    def close(self) -> None:
        pass


def _samples(perturb: Perturb, fusion: str = "early", **kw):
    from cosim.eval.dataset import EpisodeRef
    from cosim.learn.data import Samples

    s = Samples.__new__(Samples)
    s.refs = [EpisodeRef("ep", None, "all")]
    s.setup = Setup(fusion=fusion, agents="all", perturb=perturb)
    s.src = _Source(**kw)
    s._records = {}
    s.lidars = {}
    if perturb.latency:
        s._check_latency(perturb)
    return s


def test_samples_read_the_earlier_ticks_and_refuse_a_latency_off_the_tick_grid():
    s = _samples(Perturb(latency_ms=200), n_ticks=6)
    assert [len(s.item(i)["sent"]) for i in range(6)] == [0, 0, 1, 1, 1, 1]
    np.testing.assert_allclose(_collab_cloud(s.item(4)), _in_ego(s.src.records[2], s.src.records[2]["map_from"][1]),
                               atol=2e-5)
    with pytest.raises(InputError, match=r"--latency 150: not a whole number of ticks .* give a multiple of 100 ms"):
        _samples(Perturb(latency_ms=150), n_ticks=4)
    with pytest.raises(InputError, match="--latency 100: 1 tick, but the cache holds one tick in 2"):
        _samples(Perturb(latency_ms=100), n_ticks=4, every=2)
    with pytest.raises(InputError, match=r"--latency links .* needs every tick"):
        _samples(Perturb(latency_links=True), n_ticks=4, every=2)
    assert [len(_samples(Perturb(latency_ms=400), n_ticks=8, every=2).item(i)["sent"]) for i in range(4)] == [
        0, 0, 1, 1]  # 4 ticks, a multiple of the cache's 2


# ---------------------------------------------------------------------------------------------- loss

@pytest.mark.parametrize("perturb, lost", [(Perturb(loss=0.3, seed=1), 0.3), (Perturb(loss_links=True, seed=1), 0.2),
                                           (Perturb(loss=1.0), 1.0), (Perturb(loss=0.0, pose_m=0.01), 0.0)])
def test_loss_drops_the_right_share_of_messages(perturb, lost):
    n = 3000

    def _record(t: int, delivery: float) -> dict:  # the collaborator held in range, 20 m away, at every tick
        return _record_at(t, collab_xy=(20.0 - t, 6.0), delivery=delivery)

    setup = Setup(fusion="early", agents="all", perturb=perturb)
    arrived = [len(make_item(_record(t, delivery=0.8), EGO, setup, "ep")["sent"]) for t in range(n)]
    share = 1 - sum(arrived) / n
    sigma = math.sqrt(lost * (1 - lost) / n)
    assert abs(share - lost) <= 3 * sigma + 1e-12, (share, lost, sigma)
    again = [len(make_item(_record(t, delivery=0.8), EGO, setup, "ep")["sent"]) for t in range(n)]
    assert again == arrived  # the same seed: the same messages lost
    if 0 < lost < 1:
        other = Setup(fusion="early", agents="all", perturb=Perturb(**{**perturb.to_dict(), "seed": 2}))
        assert [len(make_item(_record(t, delivery=0.8), EGO, other, "ep")["sent"]) for t in range(n)] != arrived


def test_loss_links_is_what_delivery_drew_before_seeds():
    """``--loss links`` at seed 0 loses exactly the messages ``--delivery`` lost (the old Setup field reads as it)."""
    before = {k: v for k, v in Setup(fusion="early", agents="all").to_dict().items() if k != "perturb"}
    setup = Setup.from_dict({**before, "delivery": True})  # a checkpoint's setup from before the perturbations
    assert setup.perturb == Perturb(loss_links=True)
    for t in range(200):
        old_draw = smp.delivered("ep", t, COLLAB, EGO, 0.5)
        assert len(make_item(_record(t, collab_xy=(20.0 - t, 6.0), delivery=0.5), EGO, setup, "ep")["sent"]) == int(
            old_draw)
    with pytest.raises(InputError, match="no /comm/links"):
        make_item({**_record(0), "links": None}, EGO, setup, "ep")


# ---------------------------------------------------------------------------------------------- bad values

@pytest.mark.parametrize("kw, words", [
    ({"pose_m": -0.1}, "POS_M must be a finite number >= 0"), ({"pose_deg": float("nan")}, "ROT_DEG"),
    ({"loss": 1.5}, "--loss: a probability from 0 to 1"), ({"loss": -0.1}, "--loss"),
    ({"loss": float("nan")}, "--loss"), ({"latency_ms": -100}, "--latency"),
    ({"latency_ms": 100, "latency_links": True}, "not both"), ({"loss": 0.1, "loss_links": True}, "not both"),
])
def test_a_bad_perturbation_is_refused(kw, words):
    with pytest.raises(InputError, match=words):
        Perturb(**kw)


@pytest.mark.parametrize("flag, value, words", [
    ("--pose-noise", "-0.1,0", "must be >= 0, got -0.1"), ("--pose-noise", "nan,0.2", "finite"),
    ("--pose-noise", "0.2", "POS_M,ROT_DEG"), ("--loss", "1.5", "must be 0 to 1"), ("--loss", "nan", "--loss"),
    ("--latency", "-100", "--latency"), ("--latency", "0.5", "--latency"), ("--latency", "soon", "--latency"),
])
@pytest.mark.parametrize("command", ["train", "predict", "validate"])
def test_bad_flags_exit_2_with_one_line(capsys, tmp_path, command, flag, value, words):
    from tests.helpers import cli_in_process

    args = {"train": ["learn", "train", str(tmp_path), "--out", str(tmp_path / "run")],
            "predict": ["learn", "predict", str(tmp_path), str(tmp_path), "--out", str(tmp_path / "p.jsonl")],
            "validate": ["learn", "validate", str(tmp_path), str(tmp_path)]}[command]
    status, _out, err = cli_in_process(capsys, *args, f"{flag}={value}")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and words in lines[0] and flag in lines[0], err


def test_the_flags_make_the_perturbation():
    from cosim.cli import build_parser
    from cosim.learn.cli import perturb_of

    def parsed(*flags: str) -> Perturb:
        return perturb_of(build_parser().parse_args(["learn", "predict", ".", ".", "--out", "p.jsonl", *flags]))

    assert parsed() == Perturb() and not parsed()
    assert parsed("--pose-noise", "0.2,0.4", "--latency", "200", "--loss", "0.1", "--perturb-seed", "3") == Perturb(
        pose_m=0.2, pose_deg=0.4, latency_ms=200, loss=0.1, seed=3)
    assert parsed("--latency", "links", "--loss", "links") == Perturb(latency_links=True, loss_links=True)
    assert parsed("--delivery") == Perturb(loss_links=True)  # the deprecated flag: --loss links


# ---------------------------------------------------------------------------------------------- bytes sent

@pytest.mark.skipif(not HAVE_TORCH, reason="PyTorch is not installed")
def test_bytes_sent_per_fusion_mode():
    import torch

    from cosim.learn.grid import voxelise
    from cosim.learn.model import PillarDetector
    from cosim.learn.samples import agent_grid
    from cosim.learn.train import predict_and_send

    rec = _record(0)
    for fusion in ("none", "early", "late", "intermediate"):
        setup = Setup(fusion=fusion, agents="ego" if fusion == "none" else "all")
        torch.manual_seed(0)
        model = PillarDetector(setup.grid, len(setup.classes), width=8, fusion=fusion).eval()
        item = make_item(rec, EGO, setup, "ep")
        *_boxes_scores_classes, sent = predict_and_send(model, item, setup, torch.device("cpu"), score_min=0.0,
                                                       max_boxes=5)
        if fusion == "none":
            assert sent == 0
        elif fusion == "early":
            assert item["sent"] == [4] and sent == 4 * smp.POINT_BYTES == 64  # 4 points of float32 x, y, z, intensity
        elif fusion == "late":
            assert sent == 5 * smp.BOX_BYTES  # the collaborator's boxes (score >= 0 here: as many as allowed)
        else:
            pillars = len(voxelise(item["clouds"][1], agent_grid(setup.grid))[2])
            assert pillars == 4 and sent == pillars * smp.pillar_bytes(8) == 4 * (8 * 4 + 4)
