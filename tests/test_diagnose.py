"""The rig check (gbscan.diagnose, 'gbscan check'): silent on a good rig's frames, and each fault
of the simulated rig, one at a time, raises its own finding."""
import dataclasses
import json

import numpy as np
import pytest

from gbscan import sim
from gbscan.cli import main
from gbscan.decode import DecodeParams, decode
from gbscan.diagnose import FrameCheck, check_frame, findings, stripe_camera_px
from gbscan.io import read_image_rgb, write_png
from gbscan.pattern import PatternSpec, render_pattern

SPEC = PatternSpec()
BASE = dataclasses.replace(sim.preset("typical"), supersample=1)
RIG = sim.paper_rig()
PLANE = sim.scenes.plane(650.0, (10.0, 20.0))

#: one fault at a time (figures measured on the plane, sphere, head, real face and multi-object
#: scenes: see gbscan/diagnose.py's thresholds) -> the finding it must raise
FAULTS = {
    "dim": dataclasses.replace(BASE, exposure=BASE.exposure * 0.2),
    "saturated": dataclasses.replace(BASE, exposure=BASE.exposure * 3),
    "ambient": dataclasses.replace(BASE, ambient_rgb=(0.3, 0.3, 0.3)),
    "colour_balance": dataclasses.replace(BASE, proj_gain_rgb=(1.0, 1.0, 0.3)),
    "contrast": dataclasses.replace(BASE, proj_sigma_px=3.0),
    "noise": dataclasses.replace(BASE, full_well_e=500.0, read_noise_dn=3.0),
    "chroma": dataclasses.replace(BASE, yuv="yuyv"),
}


def _check(scene, cond, spec=SPEC, frame=None, params=None):
    r = sim.render(RIG, scene, render_pattern(spec) if frame is None else frame, cond, seed=0)
    sm = decode(r.image, spec, params or DecodeParams())
    return r, sm, check_frame(r.image, sm, params)


@pytest.mark.parametrize("scene", ["plane", "head"])
def test_a_good_rig_frame_raises_nothing(scene):
    sc = PLANE if scene == "plane" else sim.scenes.head()
    r, sm, c = _check(sc, BASE)
    assert c.findings == [], [f.text for f in c.findings]
    assert 20 < c.stripe_snr < 60 and c.peak_dn > 120 and c.saturated_frac == 0
    assert c.contrast > 0.85 and c.ambient_ratio < 0.1 and 0.7 < c.blue_green_ratio < 1.1
    # the stripe area: every pixel the pattern lights is in it, reported or lost in the unwrapping
    lit = r.lit & ~r.depth_edge
    assert c.stripe_area_px >= 0.97 * lit.sum()
    assert c.reported_frac == pytest.approx(sm.valid.sum() / c.stripe_area_px)
    json.dumps(c.to_dict())                                  # plain types


@pytest.mark.parametrize("fault", sorted(FAULTS))
def test_each_fault_raises_its_own_finding(fault):
    _, _, c = _check(PLANE, FAULTS[fault])
    keys = [f.key for f in c.warnings()]
    assert fault in keys, (fault, keys)
    # the cause is named, not a symptom of it: ambient light and a weak colour lower the contrast
    # too, but say so themselves
    if fault in ("ambient", "colour_balance"):
        assert "contrast" not in keys
    if fault in ("dim", "saturated", "ambient", "colour_balance", "contrast"):
        assert "noise" not in keys and "fragmented" not in keys
    assert all(f.text and f.short and f.level == "warn" for f in c.warnings())
    if fault == "chroma":   # the decoder withheld the index: the check says why, not "unindexed"
        assert c.withheld and c.chroma_subsampled and c.chroma_score < 0.5 and keys[0] == "chroma"
        assert "unindexed" not in keys and "withholds" in c.warnings()[0].text
    else:
        assert not c.chroma_subsampled and c.chroma_score > 0.7


def test_no_pattern_and_a_uniform_flood_say_no_stripes():
    black = np.zeros_like(render_pattern(SPEC))
    cyan = black.copy()
    cyan[..., 1:] = 255
    for frame in (black, cyan):
        _, _, c = _check(PLANE, BASE, frame=frame)
        assert [f.key for f in c.findings] == ["no_stripes"]


def test_stripe_width_in_the_camera_is_measured_and_checked():
    # truth: the projector column's gradient along the rows
    for px, w, key in ((4, 7, "narrow_stripes"), (8, 15, None), (32, 61, "wide_stripes")):
        spec = PatternSpec(stripe_px=px)
        r, sm, c = _check(PLANE, BASE, spec=spec, params=DecodeParams(threshold_window_px=w, norm_window_px=w))
        g = np.abs(np.gradient(r.proj_xy[..., 0], axis=1))
        truth = px / np.nanmedian(g[r.lit & ~r.depth_edge])
        assert c.stripe_camera_px == pytest.approx(truth, rel=0.05)       # measured 2.2 / 4.3 / 17.3 px
        # without decoded columns: from the colour runs (integer lengths, a little short)
        fb = stripe_camera_px(np.full_like(sm.column, np.nan), sm.labels, px)
        assert 0.8 * truth < fb <= 1.05 * truth
        keys = [f.key for f in c.findings]
        assert (key in keys) if key else not keys, keys


def test_windows_too_narrow_for_the_stripes_are_named():
    """24 px stripes (13 camera px) decoded at the frame's own size (--resample never): the rig
    check names the windows and says to let the decoder resample (or widen the windows); both
    decode the plane, and the automatic decode raises no windows finding (its windows, in frame
    pixels, are 15 x the factor)."""
    spec = PatternSpec(stripe_px=24)
    never = DecodeParams(resample=1.0)
    _, sm, c = _check(PLANE, BASE, spec=spec, params=never)
    found = {f.key: f for f in c.findings}
    assert "windows" in found and "--resample auto" in found["windows"].text
    assert "--local-window-px" in found["windows"].text
    w = int(found["windows"].text.split("--local-window-px ")[1].split()[0])
    p = DecodeParams(threshold_window_px=w, norm_window_px=w, resample=1.0)
    r, sm2, c2 = _check(PLANE, BASE, spec=spec, params=p)
    assert c2.reported_frac > c.reported_frac + 0.5                     # measured 14 % -> 98 %
    assert "windows" not in [f.key for f in c2.findings]
    r, sm3, c3 = _check(PLANE, BASE, spec=spec)
    assert 2.5 < sm3.stats["resample"] <= 3.75 and c3.window_px >= 37
    assert c3.reported_frac > c.reported_frac + 0.5                     # measured 14 % -> 96 %
    keys = [f.key for f in c3.findings]
    assert "windows" not in keys and "resampled" in keys and c3.resample == sm3.stats["resample"]
    assert [f.level for f in c3.findings if f.key == "resampled"] == ["info"] and not c3.warnings()
    assert c.resample == 1.0 and "resampled" not in found


def test_findings_follow_the_figures():
    base = dict(pixels=100, stripe_area_px=80, labelled_px=10_000, reported_frac=0.9,
                lost_frac={"isolated": 0.0, "unindexed": 0.0}, stripe_snr=30.0, noise_dn=2.0, modulation_dn=60.0,
                peak_dn=180.0, saturated_frac=0.0, contrast=0.9, ambient_ratio=0.05, blue_green_ratio=0.9,
                stripe_camera_px=4.0, window_px=15)
    assert findings(FrameCheck(**base)) == []
    for change, key in (({"blue_green_ratio": 2.5}, "colour_balance"), ({"lost_frac": {"isolated": 0.3}}, "fragmented"),
                        ({"lost_frac": {"unindexed": 0.4}}, "unindexed"), ({"stripe_snr": float("nan")}, None),
                        ({"contrast": 0.6}, "contrast"), ({"contrast": 0.6, "ambient_ratio": 0.3}, "ambient")):
        keys = [f.key for f in findings(FrameCheck(**{**base, **change}))]
        assert keys == ([key] if key else []), (change, keys)
    green = [f for f in findings(FrameCheck(**{**base, "blue_green_ratio": 2.5}))][0]
    assert "green stripes at 0.40 of the blue" in green.text


def test_check_frame_rejects_mismatched_input():
    _, sm, _ = _check(PLANE, BASE)
    with pytest.raises(ValueError, match="uint8 RGB"):
        check_frame(np.zeros((480, 640), np.uint8), sm)
    with pytest.raises(ValueError, match="differ in size"):
        check_frame(np.zeros((240, 320, 3), np.uint8), sm)


def test_check_command_prints_figures_findings_json_and_strict_status(tmp_path, capsys):
    good = tmp_path / "good.png"
    bad = tmp_path / "dim.png"
    write_png(good, sim.render(RIG, PLANE, render_pattern(SPEC), BASE, seed=0).image)
    write_png(bad, sim.render(RIG, PLANE, render_pattern(SPEC), FAULTS["dim"], seed=0).image)
    assert main(["check", str(good), "--strict"]) == 0
    out = capsys.readouterr().out
    assert "no findings" in out and "stripe SNR" in out
    js = tmp_path / "c.json"
    assert main(["check", str(bad), "--strict", "--json", str(js)]) == 3
    out = capsys.readouterr().out
    assert "warn: the stripes reach only" in out
    d = json.loads(js.read_text())
    assert d["image"] == str(bad) and [f["key"] for f in d["findings"]] == ["dim"] and d["peak_dn"] < 90
    assert main(["check", str(bad)]) == 0                                # not strict: findings are not errors
    capsys.readouterr()
    # decode and scan print the warnings as hint lines; nothing for a good frame
    assert main(["decode", str(bad), "-o", str(tmp_path / "s.npz")]) == 0
    assert "hint: the stripes reach only" in capsys.readouterr().err
    assert main(["decode", str(good), "-o", str(tmp_path / "s.npz")]) == 0
    assert "hint:" not in capsys.readouterr().err
    from gbscan.calibfile import calibration_from_rig, save_calibration

    cal = save_calibration(tmp_path / "calib.yaml", calibration_from_rig(RIG, SPEC))
    assert main(["scan", str(bad), "--calib", str(cal), "-o", str(tmp_path / "c.ply")]) == 0
    assert capsys.readouterr().err.count("hint:") == 1
    assert main(["scan", str(good), "--calib", str(cal), "-o", str(tmp_path / "c.ply")]) == 0
    assert "hint:" not in capsys.readouterr().err
    # a video or a folder of frames: --frame picks one (the frame gbscan batch names)
    from gbscan.frames import write_video

    video = write_video(tmp_path / "v.mkv", [read_image_rgb(p) for p in (good, bad)])
    assert main(["check", str(video), "--frame", "1", "--strict"]) == 3
    assert "warn: the stripes reach only" in capsys.readouterr().out
    assert main(["check", str(video), "--strict"]) == 0                   # frame 0: the good one
    capsys.readouterr()
    assert main(["check", str(tmp_path / "v.mkv"), "--frame", "2"]) == 1
    assert main(["check", str(good), "--frame", "0"]) == 1
    err = capsys.readouterr().err
    assert "--frame 2: " in err and "has frames 0 to 1" in err and "--frame applies to a video" in err
    # bad input: one line, non-zero
    assert main(["check", str(tmp_path / "missing.png")]) == 1
    assert main(["check", str(good), "--json", str(tmp_path / "no" / "c.json")]) == 1
    assert main(["check", str(good), "--json", str(tmp_path / "c.txt")]) == 1
    err = capsys.readouterr().err
    assert err.count("gbscan check: error:") == 3 and "Traceback" not in err
