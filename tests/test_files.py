"""io and the calibration file: atomic writes, strict loading, clear errors."""
import os

import numpy as np
import pytest
import yaml

from gbscan.calibfile import calibration_from_rig, load_calibration, save_calibration
from gbscan.errors import GBError
from gbscan.io import atomic_path, load_session, read_image_rgb, save_yaml, write_png, write_session_yaml
from gbscan.pattern import PatternSpec
from gbscan.rig import paper_rig


def test_atomic_write_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.yaml"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("new")
            raise RuntimeError("boom")
    assert target.read_text() == "old"


def test_atomic_write_respects_umask(tmp_path):
    old = os.umask(0o022)
    try:
        save_yaml(tmp_path / "x.yaml", {"a": 1})
    finally:
        os.umask(old)
    assert (tmp_path / "x.yaml").stat().st_mode & 0o777 == 0o644


def test_atomic_write_names_missing_folder(tmp_path):
    with pytest.raises(GBError, match="does not exist"):
        save_yaml(tmp_path / "nope" / "x.yaml", {"a": 1})


def test_calibration_round_trip(tmp_path):
    calib = calibration_from_rig(paper_rig(), PatternSpec())
    path = save_calibration(tmp_path / "calib.yaml", calib)
    back = load_calibration(path)
    np.testing.assert_array_equal(back.plane_index, calib.plane_index)
    np.testing.assert_allclose(back.plane_normal, calib.plane_normal, atol=1e-15)
    np.testing.assert_allclose(back.plane_d, calib.plane_d, atol=1e-12)
    np.testing.assert_allclose(back.camera.K, calib.camera.K)
    assert back.pattern == PatternSpec()
    raw = yaml.safe_load(path.read_text())
    assert raw["schema"] == "gbcal.calibration" and raw["version"] == 1
    assert set(raw["planes"][0]) == {"index", "column", "normal", "d"}
    assert raw["created"]["by"] and raw["units"]["length"] == "mm"


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.update(version=99), "version"),
    (lambda d: d.update(schema="other"), "schema"),
    (lambda d: d["camera"].pop("distortion"), "camera.distortion"),
    (lambda d: d["camera"].update(matrix=[[1, 0], [0, 1]]), "camera.matrix"),
    (lambda d: d["planes"][3].pop("d"), r"planes\[3\].d"),
    (lambda d: d["planes"][2].update(normal=[1, 1, 1]), "unit vector"),
    (lambda d: d.update(planes=[]), "no light planes"),
    (lambda d: d["camera"].update(width="640"), "camera.width"),
])
def test_calibration_load_is_strict(tmp_path, edit, message):
    path = save_calibration(tmp_path / "c.yaml", calibration_from_rig(paper_rig(), PatternSpec()))
    d = yaml.safe_load(path.read_text())
    edit(d)
    path.write_text(yaml.safe_dump(d))
    with pytest.raises(GBError, match=message) as e:
        load_calibration(path)
    assert str(path) in str(e.value)


def test_corrupt_yaml_is_named(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("camera: [unclosed\n")
    with pytest.raises(GBError, match="not valid YAML") as e:
        load_calibration(p)
    assert "bad.yaml" in str(e.value)


def test_images(tmp_path, monkeypatch):
    import cv2

    rgb = np.random.default_rng(3).integers(0, 256, (4, 5, 3), dtype=np.uint8)   # channel order matters
    p = write_png(tmp_path / "a.png", rgb)
    got = read_image_rgb(p)
    np.testing.assert_array_equal(got, rgb)
    assert got.flags["C_CONTIGUOUS"] and got.dtype == np.uint8
    # 16-bit colour: the high byte; 4 channels: alpha dropped
    rgb16 = (rgb.astype(np.uint16) << 8) | 0x7F
    assert cv2.imwrite(str(tmp_path / "a16.png"), np.ascontiguousarray(rgb16[:, :, ::-1]))
    np.testing.assert_array_equal(read_image_rgb(tmp_path / "a16.png"), rgb)
    bgra = np.dstack([rgb[:, :, ::-1], np.full((4, 5), 9, np.uint8)])
    assert cv2.imwrite(str(tmp_path / "a4.png"), bgra)
    np.testing.assert_array_equal(read_image_rgb(tmp_path / "a4.png"), rgb)
    with monkeypatch.context() as m:   # (no writer makes 2-channel files; a reader might return one)
        m.setattr(cv2, "imread", lambda *a: np.zeros((4, 5, 2), np.uint8))
        with pytest.raises(GBError, match="a.png has 2 channels"):
            read_image_rgb(p)
    with pytest.raises(GBError, match="5x4 but 640x480"):
        read_image_rgb(p, size=(640, 480))
    write_png(tmp_path / "g.png", rgb[..., 1])
    with pytest.raises(GBError, match="grey"):
        read_image_rgb(tmp_path / "g.png")
    (tmp_path / "c.png").write_bytes(b"not a png")
    with pytest.raises(GBError, match="could not be read"):
        read_image_rgb(tmp_path / "c.png")
    with pytest.raises(GBError, match="does not exist"):
        read_image_rgb(tmp_path / "missing.png")


def test_session_format(tmp_path):
    write_session_yaml(tmp_path, board=(9, 7, 30.0), camera_size=(640, 480), projector_size=(1024, 768),
                       frames=["white", "stripes"])
    with pytest.raises(GBError, match="no pose_000"):
        load_session(tmp_path)
    (tmp_path / "pose_000").mkdir()
    s = load_session(tmp_path)
    assert (s.board_cols, s.board_rows, s.square_mm) == (9, 7, 30.0)
    assert s.frames == ("white", "stripes") and s.frame_path(0, "white").name == "white.png"
    d = yaml.safe_load((tmp_path / "session.yaml").read_text())
    d["board"].pop("square_mm")
    (tmp_path / "session.yaml").write_text(yaml.safe_dump(d))
    with pytest.raises(GBError, match="board.square_mm"):
        load_session(tmp_path)
    os.remove(tmp_path / "session.yaml")
    with pytest.raises(GBError, match="session.yaml is missing"):
        load_session(tmp_path)


@pytest.mark.parametrize("quality", [50, 75, 90, 95, 100])
def test_jpeg_info_reads_sampling_and_quality_from_the_header(tmp_path, quality):
    import cv2

    from gbscan.io import jpeg_info

    img = np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)
    for sampling, flag in (("4:4:4", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
                           ("4:2:2", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422),
                           ("4:2:0", cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420)):
        params = [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, flag]
        cv2.imwrite(str(tmp_path / "f.jpg"), img, params)
        assert jpeg_info(tmp_path / "f.jpg") == {"sampling": sampling, "quality": quality}
    cv2.imwrite(str(tmp_path / "g.jpg"), img[..., 0], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert jpeg_info(tmp_path / "g.jpg") == {"sampling": "grey", "quality": quality}


def test_input_warning_for_frames_that_lose_the_colour_stripes(tmp_path):
    import cv2

    from gbscan.io import input_warning, jpeg_info

    img = np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)
    cases = {"420_95.jpg": (95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420),
             "444_80.jpg": (80, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444),
             "444_95.jpg": (95, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444)}
    for name, (q, flag) in cases.items():
        cv2.imwrite(str(tmp_path / name), img, [cv2.IMWRITE_JPEG_QUALITY, q, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, flag])
    w = input_warning(tmp_path / "420_95.jpg")
    assert w.startswith("warning:") and "4:2:0" in w and "420_95.jpg" in w and "PNG" in w
    w = input_warning(tmp_path / "444_80.jpg")
    assert "quality ~80" in w and "4:2:0" not in w
    assert input_warning(tmp_path / "444_95.jpg") is None
    write_png(tmp_path / "f.png", img)
    assert input_warning(tmp_path / "f.png") is None and jpeg_info(tmp_path / "f.png") is None
    # not JPEG after all, cut short, or missing: no warning and no error (reading the image reports those)
    (tmp_path / "cut.jpg").write_bytes((tmp_path / "420_95.jpg").read_bytes()[:30])
    (tmp_path / "junk.jpg").write_bytes(b"\xff\xd8\xff\xdb\x00")
    for name in ("cut.jpg", "junk.jpg", "missing.jpg"):
        assert jpeg_info(tmp_path / name) is None and input_warning(tmp_path / name) is None


def test_raw_bayer_frames_are_demosaiced_on_reading(tmp_path):
    """read_image_rgb(bayer=...): a camera's raw mosaic (8 or 16 bit, one channel) -> OpenCV's edge-aware
    demosaicing; a colour file with --bayer, or a grey one without, is one clear error."""
    import cv2

    from gbscan.io import BAYER_CODES, demosaic
    from gbscan.pattern import render_pattern
    from gbscan import sim

    rgb = sim.render(sim.paper_rig(), sim.scenes.plane(650.0), render_pattern(PatternSpec()), "clean", seed=0).image
    mosaic = np.empty(rgb.shape[:2], np.uint8)
    mosaic[0::2, 0::2], mosaic[0::2, 1::2] = rgb[0::2, 0::2, 0], rgb[0::2, 1::2, 1]   # R G
    mosaic[1::2, 0::2], mosaic[1::2, 1::2] = rgb[1::2, 0::2, 1], rgb[1::2, 1::2, 2]   # G B
    write_png(tmp_path / "raw.png", mosaic)
    got = read_image_rgb(tmp_path / "raw.png", bayer="RGGB", size=(640, 480))
    np.testing.assert_array_equal(got, demosaic(mosaic, "RGGB"))
    # the right channels: a flat green stripe area stays green (the mosaic's pattern name is OpenCV's)
    assert abs(got.astype(int) - rgb.astype(int)).mean() < 3.0
    wrong = read_image_rgb(tmp_path / "raw.png", bayer="BGGR")
    assert abs(wrong.astype(int) - rgb.astype(int)).mean() > 3 * abs(got.astype(int) - rgb.astype(int)).mean()
    cv2.imwrite(str(tmp_path / "raw16.png"), mosaic.astype(np.uint16) * 257)
    got16 = read_image_rgb(tmp_path / "raw16.png", bayer="RGGB")
    assert got16.dtype == np.uint8 and np.abs(got16.astype(int) - got.astype(int)).max() <= 1
    with pytest.raises(GBError, match="drop --bayer"):
        read_image_rgb(write_png(tmp_path / "rgb.png", rgb), bayer="RGGB")
    with pytest.raises(GBError, match="--bayer PATTERN"):
        read_image_rgb(tmp_path / "raw.png")
    with pytest.raises(GBError, match="Bayer pattern must be one of"):
        demosaic(mosaic, "RGBW")
    with pytest.raises(GBError, match="one 8- or 16-bit channel"):
        demosaic(rgb, "RGGB")
    assert set(BAYER_CODES) == {"RGGB", "BGGR", "GRBG", "GBRG"}
