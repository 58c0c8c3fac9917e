"""Frame sources: folders of images and video files, numbering, selection, bad input."""
import numpy as np
import pytest

from gbscan.errors import GBError
from gbscan.frames import FolderFrames, VideoFrames, open_frames, select, write_video
from gbscan.io import write_png


def _frames(n, h=48, w=64, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def test_select_is_a_slice():
    assert list(select(10, 2, 8, 3)) == [2, 5]
    assert list(select(10, -3)) == [7, 8, 9]
    assert list(select(5, 0, None, 1)) == [0, 1, 2, 3, 4]
    with pytest.raises(GBError, match="--every"):
        select(10, every=0)


def test_folder_natural_order_and_ignored(tmp_path):
    imgs = _frames(3)
    for name, img in zip(["f10.png", "f2.png", "f1.png"], imgs):
        write_png(tmp_path / name, img)
    (tmp_path / "notes.txt").write_text("not a frame")
    (tmp_path / ".hidden.png").write_bytes(b"x")
    src = open_frames(tmp_path)
    assert isinstance(src, FolderFrames) and src.random_access
    assert [r.source for r in src.refs()] == ["f1.png", "f2.png", "f10.png"]
    assert src.ignored == ("notes.txt",)
    got = dict((r.index, img) for r, img in src.frames(src.refs()))
    np.testing.assert_array_equal(got[0], imgs[2])
    np.testing.assert_array_equal(got[2], imgs[0])


def test_folder_bad_frames_are_per_frame_errors(tmp_path):
    a, b = _frames(2)
    write_png(tmp_path / "0.png", a)
    write_png(tmp_path / "1.png", np.zeros((10, 10, 3), np.uint8))  # wrong size
    (tmp_path / "2.png").write_bytes(b"not a png")                  # unreadable
    write_png(tmp_path / "3.png", b[:, :, 0])                        # grey
    src = open_frames(tmp_path)
    out = list(src.frames(src.refs(), size=(64, 48)))
    assert isinstance(out[0][1], np.ndarray)
    assert isinstance(out[1][1], GBError) and "10x10" in str(out[1][1]) and "64x48" in str(out[1][1])
    assert isinstance(out[2][1], GBError) and "could not be read" in str(out[2][1])
    assert isinstance(out[3][1], GBError) and "grey" in str(out[3][1])


@pytest.mark.parametrize("fourcc,ext", [("FFV1", "avi"), ("FFV1", "mkv")])
def test_video_round_trip_exact(tmp_path, fourcc, ext):
    imgs = _frames(7, seed=1)
    path = write_video(tmp_path / f"v.{ext}", imgs, fourcc=fourcc)
    src = open_frames(path)
    assert isinstance(src, VideoFrames) and not src.random_access
    assert len(src) == 7 and (src.width, src.height) == (64, 48)
    refs = src.refs(1, None, 2)
    assert [r.index for r in refs] == [1, 3, 5] and refs[0].source == f"v.{ext}#1"
    for r, img in src.frames(refs):
        np.testing.assert_array_equal(img, imgs[r.index])  # lossless, RGB order kept


def test_input_warning_for_jpeg_frames_and_chroma_subsampled_video(tmp_path):
    import cv2

    imgs = _frames(3, seed=2)
    for i, img in enumerate(imgs):
        cv2.imwrite(str(tmp_path / f"f{i}.jpg"), img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])
    w = FolderFrames(tmp_path).input_warning()
    assert "4:2:0" in w and "f0.jpg" in w and "(3 JPEG frames)" in w
    png = tmp_path / "png"
    png.mkdir()
    write_png(png / "a.png", imgs[0])
    assert FolderFrames(png).input_warning() is None
    lossless = open_frames(write_video(tmp_path / "v.mkv", imgs))
    assert lossless.input_warning() is None
    mjpg = open_frames(write_video(tmp_path / "v.avi", imgs, fourcc="MJPG"))
    assert mjpg.codec == "MJPG" and mjpg.pixel_format == "I420"
    assert "4:2:0" in mjpg.input_warning() and "MJPG" in mjpg.input_warning()


def test_folder_of_raw_bayer_frames(tmp_path):
    from gbscan.io import demosaic

    raws = [np.random.default_rng(k).integers(0, 256, (48, 64), dtype=np.uint8) for k in range(2)]
    for k, r in enumerate(raws):
        write_png(tmp_path / f"r{k}.png", r)
    src = open_frames(tmp_path, bayer="BGGR")
    out = list(src.frames(src.refs(), size=(64, 48)))
    for (ref, img), raw in zip(out, raws):
        assert ref.bayer == "BGGR"
        np.testing.assert_array_equal(img, demosaic(raw, "BGGR"))
    assert isinstance(list(open_frames(tmp_path).frames(src.refs()[:1]))[0][1], np.ndarray)  # the ref carries it
    plain = list(open_frames(tmp_path).frames(open_frames(tmp_path).refs()))
    assert all(isinstance(img, GBError) and "--bayer" in str(img) for _, img in plain)
    video = write_video(tmp_path / "v.mkv", _frames(2))
    with pytest.raises(GBError, match="applies to a folder of raw frames"):
        open_frames(video, bayer="RGGB")


def test_video_wrong_size_and_past_end(tmp_path):
    path = write_video(tmp_path / "v.avi", _frames(3))
    src = open_frames(path)
    out = list(src.frames(src.refs(), size=(640, 480)))
    assert all(isinstance(e, GBError) and "640x480" in str(e) for _, e in out)
    src.n_frames = 5  # a container that announces more frames than it holds
    out = list(src.frames(src.refs()))
    assert [isinstance(x, np.ndarray) for _, x in out] == [True, True, True, False, False]
    assert "ended" in str(out[3][1])


def test_bad_inputs(tmp_path):
    with pytest.raises(GBError, match="does not exist"):
        open_frames(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(GBError, match="holds no images"):
        open_frames(tmp_path / "empty")
    (tmp_path / "bad.avi").write_bytes(b"\x00garbage" * 100)
    with pytest.raises(GBError, match="could not be opened"):
        open_frames(tmp_path / "bad.avi")
    write_png(tmp_path / "one.png", _frames(1)[0])
    with pytest.raises(GBError, match="single image"):
        open_frames(tmp_path / "one.png")
    with pytest.raises(GBError, match="no frames"):
        write_video(tmp_path / "x.avi", [])
    with pytest.raises(GBError, match="not available"):
        write_video(tmp_path / "x.avi", _frames(2), fourcc="LAGS")  # no encoder in opencv-headless
    with pytest.raises(GBError, match="every frame must be"):
        write_video(tmp_path / "x.avi", _frames(1) + _frames(1, h=32))
    assert not list(tmp_path.glob("*x.avi*"))  # neither the output nor a temporary left behind
