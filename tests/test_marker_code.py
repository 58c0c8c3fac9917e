"""The marker code (gbscan.pattern): patterns wider than 167 stripes (a 1920-px projector at 8 px)
keep their absolute index, and a pattern made before keeps decoding as it was projected."""
import dataclasses
import subprocess
import sys

import numpy as np
import pytest

from gbscan import sim
from gbscan.calibfile import calibration_from_rig, load_calibration, save_calibration
from gbscan.decode import DecodeParams, decode
from gbscan.errors import GBError
from gbscan.io import read_image_rgb
from gbscan.pattern import (CODES_AGREE_STRIPES, FIRST_MARKER, MARKER_CODE, MARKER_GAPS, PAIR_SPACING, PatternSpec,
                            marker_gap_symbols, render_pattern)

#: the paper pattern's markers (1024 px, 8 px a stripe), as every release has projected them
PAPER_MARKERS = [3, 7, 11, 16, 20, 26, 30, 37, 41, 49, 54, 59, 65, 70, 77, 82, 90, 96, 102, 109, 115, 123]


def _period(spec: PatternSpec, min_overlap: int = 20):
    # the smallest even shift t under which the markers repeat over at least min_overlap stripes
    m = spec.is_marker()
    n = spec.n_stripes
    for t in range(2, n - min_overlap, 2):
        if np.array_equal(m[t:], m[:n - t]):
            return t
    return None


def test_paper_pattern_markers_unchanged():
    # a calibration or a frame made with any earlier version decodes as before
    assert PatternSpec().marker_indices().tolist() == PAPER_MARKERS
    assert PatternSpec(marker_code=1).marker_indices().tolist() == PAPER_MARKERS


def test_codes_agree_up_to_167_stripes_then_differ():
    for n in range(FIRST_MARKER + 3, CODES_AGREE_STRIPES + 1):
        a = PatternSpec(8 * n, 600, 8, marker_code=1).marker_indices()
        b = PatternSpec(8 * n, 600, 8).marker_indices()
        assert np.array_equal(a, b), n
    n = CODES_AGREE_STRIPES + 1
    assert not np.array_equal(PatternSpec(8 * n, 600, 8, marker_code=1).marker_indices(),
                              PatternSpec(8 * n, 600, 8).marker_indices())


def test_code_1_is_periodic_beyond_167_stripes_code_2_is_not():
    # why code 2 exists: at 1920 px the old markers repeat every 154 stripes, so a region that
    # does not reach the pattern's middle fits two offsets equally
    assert _period(PatternSpec(1920, 1080, 8, marker_code=1)) == 154
    for w, px in ((1920, 8), (2560, 8), (3840, 8), (3840, 6)):
        assert _period(PatternSpec(w, 1080, px)) is None, (w, px)


def test_code_2_any_four_consecutive_markers_fix_the_position():
    sym = marker_gap_symbols(2)
    assert sym[:26] == marker_gap_symbols(1)            # code 1's B(5, 2) and its first symbol again
    triples = [sym[i:i + 3] for i in range(len(sym) - 2)]
    assert len(set(triples)) == len(triples)
    assert FIRST_MARKER + sum(MARKER_GAPS[s] for s in sym) == 639   # stripes the sequence spans
    # the first 26 symbols: every pair distinct (three markers fix the position there)
    pairs = [sym[i:i + 2] for i in range(25)]
    assert len(set(pairs)) == 25
    # the walk keeps a pair from recurring within PAIR_SPACING gaps while it can (the first 90
    # symbols), then only the three-gap rule holds
    seen = {}
    for i in range(90 - 1):
        p = sym[i:i + 2]
        if p in seen:
            assert i - seen[p] > PAIR_SPACING, (i, p)
        seen[p] = i
    # as markers of a 3840-px pattern: every window of four consecutive markers is unique
    m = PatternSpec(3840, 2160, 8).marker_indices()
    gaps = np.diff(m)
    wins = [tuple(gaps[i:i + 3]) for i in range(len(gaps) - 2)]
    assert len(set(wins)) == len(wins)


def test_marker_code_spelling_and_validation():
    # where the codes agree the spec carries the default, so old and new specs compare equal
    assert PatternSpec(marker_code=1) == PatternSpec()
    assert PatternSpec(1920, 1080, 8, markers=False, marker_code=1).marker_code == MARKER_CODE
    assert PatternSpec(1920, 1080, 8, marker_code=1).marker_code == 1
    assert PatternSpec(1920, 1080, 8, marker_code=1) != PatternSpec(1920, 1080, 8)
    for bad in (0, 3, True, "2", 2.0):
        with pytest.raises(GBError, match="marker code"):
            PatternSpec(1920, 1080, 8, marker_code=bad)
    # a mapping written before the field existed is the sequence it was projected with
    old = {"width": 1920, "height": 1080, "stripe_px": 8, "markers": True}
    assert PatternSpec.from_dict(old).marker_code == 1
    for spec in (PatternSpec(), PatternSpec(1920, 1080, 8), PatternSpec(1920, 1080, 8, marker_code=1)):
        assert PatternSpec.from_dict(spec.to_dict()) == spec


def test_calibration_file_keeps_the_code(tmp_path):
    rig = sim.paper_rig(projector_px=(1920, 1080))
    for code in (1, 2):
        cal = calibration_from_rig(rig, PatternSpec(1920, 1080, 8, marker_code=code))
        path = save_calibration(tmp_path / f"c{code}.yaml", cal)
        assert load_calibration(path).pattern.marker_code == code
    # a file written before the field existed: code 1
    text = (tmp_path / "c2.yaml").read_text()
    assert "marker_code: 2" in text
    (tmp_path / "old.yaml").write_text(text.replace(", marker_code: 2", ""))
    assert load_calibration(tmp_path / "old.yaml").pattern.marker_code == 1
    # a code this version does not know: the file and the field named
    (tmp_path / "bad.yaml").write_text(text.replace("marker_code: 2", "marker_code: 7"))
    with pytest.raises(GBError, match=r"bad.yaml: field 'pattern' .*marker code must be one of 1, 2, got 7"):
        load_calibration(tmp_path / "bad.yaml")


def test_paper_rig_projector_px():
    rig = sim.paper_rig(projector_px=(1920, 1080))
    assert (rig.projector.width, rig.projector.height) == (1920, 1080)
    np.testing.assert_allclose(rig.projector.K, [[3487.5, 0, 959.5], [0, 3487.5, 539.5], [0, 0, 1]])
    # the default is the paper's projector
    np.testing.assert_array_equal(sim.paper_rig().projector.K, [[1860, 0, 511.5], [0, 1860, 383.5], [0, 0, 1]])
    with pytest.raises(GBError, match="projector_px"):
        sim.paper_rig(projector_px=(1920.5, 1080))


def test_pattern_command_writes_the_calibrations_pattern(tmp_path):
    spec = PatternSpec(1920, 1080, 8, marker_code=1)
    calib = save_calibration(tmp_path / "c.yaml", calibration_from_rig(sim.paper_rig(projector_px=(1920, 1080)), spec))
    out = tmp_path / "p.png"
    r = subprocess.run([sys.executable, "-m", "gbscan.cli", "pattern", "-o", str(out), "--calib", str(calib)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "marker code 1" in r.stdout
    assert np.array_equal(read_image_rgb(out), render_pattern(spec))
    # a calibration without a pattern: one line, exit 1, nothing written
    cal = dataclasses.replace(load_calibration(calib), pattern=None)
    bare = save_calibration(tmp_path / "bare.yaml", cal)
    r = subprocess.run([sys.executable, "-m", "gbscan.cli", "pattern", "-o", str(tmp_path / "q.png"), "--calib", str(bare)],
                       capture_output=True, text=True)
    assert r.returncode == 1 and "records no pattern" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "q.png").exists()


@pytest.fixture(scope="module")
def hd_multi_object():
    """The multi-object scene through a 1920x1080 projector and a 1280x1024 camera behind the
    paper rig's lenses (3.7-4.1 camera px a stripe), one trace rendered under both codes."""
    rig = sim.paper_rig(projector_px=(1920, 1080), camera_px=(1280, 1024))
    cond = dataclasses.replace(sim.preset("typical"), supersample=2)
    tr = sim.trace(rig, sim.scenes.multi_object(650.0), cond)
    return {code: sim.render_traced(rig, tr, render_pattern(PatternSpec(1920, 1080, 8, marker_code=code)), seed=0)
            for code in (1, 2)}


def _decoded(r, code):
    sm = decode(r.image, PatternSpec(1920, 1080, 8, marker_code=code), DecodeParams())
    _, bad = sim.column_errors(sm.column, sm.valid, r.proj_xy[..., 0], 8)
    cand = r.lit & ~r.depth_edge
    return sm, float((sm.valid & cand).sum() / cand.sum()), int((bad & ~r.depth_edge).sum())


def test_wide_pattern_indexes_regions_off_the_middle(hd_multi_object):
    # code 1: the objects off the pattern's middle fit two offsets 154 stripes apart and are
    # dropped ("ambiguous offset"), never guessed; code 2 indexes them
    sm1, rep1, wrong1 = _decoded(hd_multi_object[1], 1)
    sm2, rep2, wrong2 = _decoded(hd_multi_object[2], 2)
    assert wrong1 == 0 and wrong2 == 0
    assert sm1.stats["region_why"].get("ambiguous offset", 0) > sm2.stats["region_why"].get("ambiguous offset", 0)
    assert rep2 > rep1 + 0.08, (rep1, rep2)     # measured 0.777 -> 0.893 at supersample 3


def test_frame_of_the_new_code_decoded_with_the_old_loses_pixels_not_stripes(hd_multi_object):
    # a calibration made before (code 1) with a pattern written since: its markers do not fit
    # the regions beyond stripe 167; they are dropped
    sm, rep, wrong = _decoded(hd_multi_object[2], 1)
    assert wrong == 0
    assert sm.stats["region_why"].get("markers do not fit the pattern", 0) >= 1


def test_rig_arguments_take_the_projector():
    import argparse

    from gbscan.cli_common import add_rig_arguments, rig_from_args, rig_label

    p = argparse.ArgumentParser()
    add_rig_arguments(p)
    args = p.parse_args(["--projector", "1920x1080", "--camera", "1280x1024"])
    rig = rig_from_args(args)
    assert (rig.projector.width, rig.projector.height, rig.camera.width) == (1920, 1080, 1280)
    assert rig_label(args) == ", camera 1280x1024, projector 1920x1080"
    assert rig_label(p.parse_args([])) == ""
    with pytest.raises(SystemExit):
        p.parse_args(["--projector", "40x30"])
