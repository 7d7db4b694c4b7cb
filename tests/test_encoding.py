"""Image and depth encoders (sensors/encoding.py, cosim/depth.py) and the default tick's size
(docs/episode_format.md section 7): lossless where the format says so, JPEG within its documented
error, the same bytes on every run."""

from __future__ import annotations

import io

import numpy as np
import pytest
from cosim.sensors import SensorSuite
from cosim.sensors.encoding import PackedLabels, encode_jpeg, encode_png, submit_encode
from cosim.sensors.synthetic import synthetic_snapshot, synthetic_world
from PIL import Image

from cosim.depth import decode_depth, encode_depth
from cosim.errors import CosimError, FormatError
from cosim.io.sensor_messages import frame_records
from cosim.io.writer import EpisodeWriter
from cosim.scenario.model import (
    AgentsSpec,
    CameraSpec,
    CommSpec,
    HoverDrone,
    OutputSpec,
    RigSpec,
    RsuAgents,
    Scenario,
    SensorsSpec,
    VehicleAgents,
    default_drone_rig,
    default_rsu_rig,
    default_vehicle_rig,
)

#: [dB] the least PSNR of a default-quality JPEG of a 1280x720 frame against its lossless image
#: (docs/episode_format.md 3.5)
JPEG_MIN_PSNR_DB = 36.0
#: [bytes] per camera pixel of a default tick of the small rig below: 0.361 with format 1.4's depth codes,
#: LiDAR in firing order and JPEG Huffman tables per image (format 1.3: 0.378); the paper rig at 1280x720 of
#: the default scenario: 0.31 (15.56 MB per tick, docs/episode_format.md 7)
MAX_BYTES_PER_CAMERA_PIXEL = 0.375

W, H = 256, 144


def _small(rig: RigSpec) -> RigSpec:
    cams = [CameraSpec(name=c.name, width=W, height=H, mount=c.mount, gimbal=c.gimbal) for c in rig.cameras]
    return rig.model_copy(update={"cameras": cams, "lidar": None})


@pytest.fixture(scope="module")
def scenario() -> Scenario:
    return Scenario(
        name="encoding",
        agents=AgentsSpec(vehicles=VehicleAgents(count=1), rsus=RsuAgents(count=1), drones=[HoverDrone()]),
        sensors=SensorsSpec(vehicle=_small(default_vehicle_rig()), rsu=_small(default_rsu_rig()),
                            drone=_small(default_drone_rig()), bev_cell_m=1.0),
        comm=CommSpec(enabled=False),
    )


@pytest.fixture(scope="module")
def frames(scenario):
    with SensorSuite(scenario, synthetic_world(), encode_images=False) as suite:
        return suite.render(synthetic_snapshot(n_vehicles=1, n_rsus=1, n_drones=1), np.random.default_rng(0))


@pytest.fixture(scope="module")
def full_size():
    """Two 1280x720 frames (a vehicle's and an RSU's front camera), the size the PSNR is documented for."""
    rigs = {k: r.model_copy(update={"lidar": None, "cameras": r.cameras[:1]})
            for k, r in (("vehicle", default_vehicle_rig()), ("rsu", default_rsu_rig()))}
    sc = Scenario(name="psnr", agents=AgentsSpec(vehicles=VehicleAgents(count=1), rsus=RsuAgents(count=1), drones=[]),
                  sensors=SensorsSpec(**rigs, bev=False), comm=CommSpec(enabled=False))
    with SensorSuite(sc, synthetic_world(), encode_images=False) as suite:
        fs = suite.render(synthetic_snapshot(n_vehicles=1, n_rsus=1, n_drones=0), np.random.default_rng(0))
    return [c.rgb for c in _cameras(fs)]


def _cameras(frames):
    return [c for af in frames.agents.values() for c in af.cameras.values()]


def _psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / mse))


def test_png_is_bit_exact_through_an_independent_decoder_and_the_same_on_every_run(frames):
    for cam in _cameras(frames):
        for img in (cam.rgb, cam.semantic):
            data = encode_png(img)
            with Image.open(io.BytesIO(data)) as im:
                assert np.array_equal(np.asarray(im), img)
            assert encode_png(img.copy()) == data
    with pytest.raises(CosimError, match="uint8"):
        encode_png(np.zeros((4, 4), np.uint16))


def test_jpeg_is_within_the_documented_psnr_and_deterministic(frames, full_size):
    quality = OutputSpec().jpeg_quality
    for rgb in full_size:
        assert rgb.shape == (720, 1280, 3)
        data = encode_jpeg(rgb, quality)
        assert data[:2] == b"\xff\xd8" and encode_jpeg(rgb.copy(), quality) == data
        with Image.open(io.BytesIO(data)) as im:
            back = np.asarray(im.convert("RGB"))
        assert back.shape == rgb.shape
        assert JPEG_MIN_PSNR_DB <= _psnr_db(rgb, back) < 60  # lossy, but close
        assert len(data) < 0.3 * len(encode_png(rgb))
    assert submit_encode(_cameras(frames)[0].rgb, "png").result() == encode_png(_cameras(frames)[0].rgb)
    with pytest.raises(CosimError, match="known: jpeg, png"):
        submit_encode(_cameras(frames)[0].rgb, "webp")


def test_compact_depth_is_lossless_on_the_stored_grid_and_refuses_bad_bytes(frames):
    from cosim.sensors.encoding import encode_depth as compiled

    from cosim.io.sensor_messages import depth_image

    for cam in _cameras(frames):
        data = encode_depth(cam.depth)
        assert compiled(cam.depth) == data  # the writer's one-pass kernel gives the reference's bytes
        back = decode_depth(data)
        assert np.array_equal(back, depth_image(cam.depth), equal_nan=True)  # the 32FC1 image, bit for bit
        assert np.isnan(back).any() == (~np.isfinite(cam.depth)).any()
        assert len(data) < 0.5 * cam.depth.nbytes
    far = np.full((3, 5), 1234.5678, np.float32)
    far[1, 2] = np.inf
    halves = (np.arange(15, dtype=np.float32).reshape(3, 5) + 0.5) / 1024  # rint's ties to even, both ways
    assert compiled(far) == encode_depth(far) and compiled(halves) == encode_depth(halves)
    back = decode_depth(encode_depth(far))
    assert np.isnan(back[1, 2]) and back[0, 0] == np.float32(round(1234.5678 * 1024) / 1024)
    with pytest.raises(FormatError, match="cosim-depth"):
        decode_depth(b"PNG....")
    with pytest.raises(FormatError, match="5x3"):
        decode_depth(encode_depth(far)[:-4])


def _cdp1(depth_m: np.ndarray) -> bytes:
    """Format 1.2 and 1.3's ``cosim-depth`` (``CDP1``), built from its documented layout: the four byte planes of
    the zigzag-coded residuals under one zstd frame (docs/episode_format.md 3.5)."""
    import struct

    import zstandard

    c = np.rint(depth_m.astype(np.float32) * np.float32(1024)).astype(np.float64)
    c[~np.isfinite(c)] = 0
    c = c.astype(np.int64)
    p = np.pad(c, ((1, 0), (1, 0)))
    r = c - p[:-1, 1:] - p[1:, :-1] + p[:-1, :-1]
    z = ((r << 1) ^ (r >> 63)).astype("<u4")
    planes = np.moveaxis(z.view(np.uint8).reshape(*c.shape, 4), 2, 0).tobytes()
    return struct.pack("<4sII", b"CDP1", c.shape[1], c.shape[0]) + zstandard.ZstdCompressor(level=1).compress(planes)


def test_compact_depth_codes_small_residuals_in_two_bits_and_older_files_still_decode(frames):
    """Format 1.4's ``CDP2`` keeps residuals 0, -1 and 1 as 2-bit codes and the rest as escapes; ``CDP1`` images of
    format 1.2 and 1.3 episodes decode to the same depth."""
    cam = _cameras(frames)[0]
    data = encode_depth(cam.depth)
    assert data[:4] == b"CDP2"
    old = _cdp1(cam.depth)
    assert np.array_equal(decode_depth(old), decode_depth(data), equal_nan=True)
    assert len(data) < 0.9 * len(old)
    steps = np.array([[0.0, 1.0, 1.0 + 2**-10, 1.0 - 2**-10, 1.0, 70000.0, np.nan]], np.float32)  # escapes both ways
    for d in (steps, steps.T, np.full((1, 1), 3.0, np.float32)):
        assert np.array_equal(decode_depth(encode_depth(d)), decode_depth(_cdp1(d)), equal_nan=True)
    back = decode_depth(encode_depth(steps))[0]
    assert np.array_equal(back[1:6], steps[0, 1:6]) and np.isnan(back[[0, 6]]).all()  # on the grid: exact


def test_a_default_tick_is_small_per_camera_pixel_and_the_lossless_option_is_one_key_away(scenario, frames,
                                                                                           tmp_path):
    """The scenario defaults (JPEG RGB, compact depth, float32 LiDAR) under the episode's zstd chunks; PNG is
    bigger but decodes to the rendered pixels."""
    out = scenario.output
    n_px = sum(c.width * c.height for c in _cameras(frames))
    sizes = {}
    for fmt in ("jpeg", "png"):
        path = tmp_path / f"{fmt}.mcap"
        with EpisodeWriter(path, compression=out.compression) as w:
            for topic, rec in frame_records(frames, 0, image_format=fmt, jpeg_quality=out.jpeg_quality,
                                            lidar_positions=scenario.sensors.lidar_positions,
                                            depth_format=out.depth_format):
                w.write(topic, rec, 0)
            sizes[fmt] = w.finish().stat().st_size
    assert (out.image_format, out.depth_format, scenario.sensors.lidar_positions) == ("jpeg", "compressed", "float32")
    assert sizes["jpeg"] / n_px <= MAX_BYTES_PER_CAMERA_PIXEL
    assert sizes["png"] > 2 * sizes["jpeg"]
    from mcap.reader import make_reader

    from cosim.io.decode import decode

    cam = frames.agents["vehicle_0"].cameras["front"]
    topics = ["/vehicle_0/front/image", "/vehicle_0/front/depth"]
    with open(tmp_path / "png.mcap", "rb") as f:
        got = {ch.topic: decode(sch.name, ch.message_encoding, m.data, sch.data)
               for sch, ch, m in make_reader(f).iter_messages(topics=topics)}
    assert got["/vehicle_0/front/image"].encoding == "png"
    assert np.array_equal(got["/vehicle_0/front/image"].array, cam.rgb)
    assert got["/vehicle_0/front/depth"].encoding == "cosim-depth"


def test_a_suite_that_releases_pixels_writes_the_same_bytes_and_keeps_no_camera_array(scenario):
    """The episode runner's suite encodes RGB and depth and packs the label images as each camera is rendered,
    letting go of every camera array; the records (visibility included) are the same bytes."""
    snap = synthetic_snapshot(n_vehicles=1, n_rsus=1, n_drones=1)
    out = []
    for release in (False, True):
        with SensorSuite(scenario, synthetic_world(), release_pixels=release) as suite:
            fs = suite.render(snap, np.random.default_rng(3))
            cams = _cameras(fs)
            assert all((c.rgb is None and c.depth is None and c.semantic is None and c.instance is None) == release
                       for c in cams)
            if release:
                packed = sum(len(c.encoded.semantic.data) + len(c.encoded.instance.data) for c in cams)
                assert packed < 0.1 * sum(5 * c.width * c.height for c in cams)
            recs = frame_records(fs, 0, image_format=scenario.output.image_format, depth_format="compressed")
            out.append([(t, bytes(r.data) if hasattr(r, "data") else r.SerializeToString(deterministic=True)
                         if hasattr(r, "SerializeToString") else r) for t, r in recs])
    assert out[0] == out[1]
    with SensorSuite(scenario, synthetic_world(), release_pixels=True) as suite:
        fs = suite.render(snap, np.random.default_rng(3))
        with pytest.raises(CosimError, match="released"):
            list(frame_records(fs, 0, image_format="png"))


def test_packed_labels_give_back_the_exact_pixels_in_place_or_cast():
    rng = np.random.default_rng(5)
    inst = np.repeat(rng.integers(0, 2**32, (9, 1), dtype=np.uint32), 40, axis=1)
    inst[3, 7] = 2**31 + 5
    p = PackedLabels.of(inst)
    assert np.array_equal(p.unpack(), inst)
    buf = np.zeros(inst.nbytes + 3, np.uint8)  # a view at an odd offset, as inside a message buffer
    view = buf[1:1 + inst.nbytes].view(np.uint8)
    p.into(view.view("<u4").reshape(inst.shape))
    assert buf[0] == 0 and buf[-2:].tolist() == [0, 0]
    assert view.tobytes() == inst.astype("<u4").tobytes()
    as_int32 = np.empty(inst.shape, np.int32)
    p.into(as_int32)
    assert np.array_equal(as_int32, inst.astype(np.int32))
