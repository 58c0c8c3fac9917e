"""One camera frame of the green-blue stripe pattern -> a :class:`StripeMap` (the decoder).

Pipeline (each step a named function; the paper's steps 1-4, then beyond the paper):

1. :func:`motion_blur` -- directional Gaussian along the stripe direction (paper's "motion
   blurring"): averages noise and texture along stripes without smearing across them.
2. :func:`colour_balance` -- ``c_i = C_i / mean_window(C_i)`` for green and blue (red ignored).
3. :func:`classify` -- green / blue by ``d = (g - b)/(g + b)`` against its local mean (paper's local
   thresholding; ``threshold="global"`` compares with 0), cyan markers where both channels are
   near their local maxima; "none" for dark (shadow), saturated and low-contrast pixels.
4. :func:`gbscan.unwrap.unwrap` -- the paper's seven unwrapping steps (relative stripe index per
   connected region).
5. :func:`gbscan.unwrap.index_regions` -- absolute index per region from the cyan markers (after
   the weld repairs, the regions left ambiguous by the pixel margin whose other offsets all
   contradict enough more stripes: :func:`gbscan.unwrap.index_by_stripes`); regions
   and small components the markers cannot index alone are indexed through the reported pixels
   around them where the projector column continues unambiguously
   (:func:`gbscan.unwrap.link_components`), else dropped and counted.  Rows whose own markers
   contradict their region's offset (a strip of another surface welded in) are dropped as
   unindexed (:func:`gbscan.unwrap.marker_conflicts`; before linking, and for the linked regions
   after it).
6. :func:`subpixel_boundaries` + column interpolation -- stripe boundaries to a fraction of a
   camera pixel, refined by a local fit along the row (:func:`fit_boundaries`), then each
   pixel's continuous projector column; the rim rules (:func:`rim_rule`), then the one-pixel
   stripe transitions step 3 called dark are reported where both neighbours are
   (``DecodeParams.join_transitions``), then the final masks and the guards.

Steps 1-6 run on the frame's lit window (:func:`lit_window`, ``DecodeParams.crop``): outside the
bounding box of the pixels bright enough to carry signal, grown by the steps' reach, every pixel
is dark, so the window alone gives the whole frame's result (positions along the rows are computed
in the frame's coordinates, the same float rounding); the colour balance and the blur's SNR are
measured on the whole frame first.

Conventions: image ``(H, W, 3)`` RGB, arrays indexed ``[v, u]``, pixel centres at integers,
projector columns in projector px with boundary ``k`` at ``k * stripe_px - 0.5``.
"""
from __future__ import annotations

import collections
import dataclasses
import functools
import json
import math
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .errors import GBError
from .pattern import PatternSpec
from .unwrap import UnwrapParams

#: Mask reason codes (``StripeMap.mask``); 0 means the pixel is reported.
OK, DARK, SATURATED, LOW_CONTRAST, ISOLATED, INCONSISTENT, UNINDEXED, NO_BOUNDARY, RIM = range(9)
REASONS = {
    OK: "ok",
    DARK: "dark",                   # no signal: shadow, background, too little light
    SATURATED: "saturated",         # a colour channel clipped: the boundary position is unreliable
    LOW_CONTRAST: "low_contrast",   # ambiguous colour: no clear green/blue modulation
    ISOLATED: "isolated",           # not linked to a region / region too small
    INCONSISTENT: "inconsistent",   # disagrees with its vertical neighbours (step 7)
    UNINDEXED: "unindexed",         # region whose absolute index is not certain
    NO_BOUNDARY: "no_boundary",     # not enclosed by located boundaries (segment end, image border)
    RIM: "rim",                     # at a silhouette / bend: the along-stripe blur biases the column
}


#: DecodeParams.subsampled_chroma's choices
SUBSAMPLED_CHROMA = ("withhold", "decode", "off")
#: a frame decoded shrunk by at least this (DecodeParams.resample: a camera with more pixels than
#: the stripes need) is not checked for chroma subsampling, and reported: each decoded pixel
#: averages whole pixel pairs.
#: Measured (scripts/resample_study.py --yuv, twenty-first session): see docs/method.md, "Camera frames"
SUBSAMPLED_CHROMA_SHRINK = 2.0


@dataclass(frozen=True)
class DecodeParams:
    """Decoder parameters (px are camera pixels).

    blur_sigma_along_px, blur_sigma_across_px : Gaussian sigma along / across the stripes.
        ``blur_sigma_along_px=None`` (the default) chooses it per frame from the frame's stripe
        signal-to-noise ratio (:func:`auto_blur_sigma`): the blur averages noise along the stripes
        but pulls the boundaries where stripes bend or end, so a clean frame wants little of it and
        a noisy one more.
    blur_auto_gain_px, blur_auto_min_px, blur_auto_max_px : the automatic sigma is
        ``clip(blur_auto_gain_px / SNR, min, max)`` in steps of 0.25 px.  Measured on the
        simulator's 35-scene sweep (``scripts/sweep_decode.py``): the typical preset (SNR ~20-40)
        decodes best at sigma ~1 (sphere/head scans: depth RMS 0.143/0.272 -> 0.116/0.234 mm, 2-2.5
        points more kept; sweep wrong pixels 14 -> 0 off depth edges, 400 -> 202 on them), the hard
        preset (SNR ~4-8) at 2.5-3 (plane 67 -> 72 %, step 80 -> 83 % reported), against the fixed
        2 px used before.  The index is not equally robust at every sigma in between: see
        ``scripts/sweep_decode.py --blur-grid``.
    stripe_angle_deg : stripe direction in the image, 0 = vertical (fast separable path).
    balance_window_px : colour-balance window (odd int); 0/None = whole image (uniform objects).
    threshold : "local" (d against its local mean) or "global" (d against 0).
    threshold_window_px : window of the local mean of d (should span >= 2 stripe periods).
    norm_window_px : horizontal window of the local min/max used for contrast, cyan and the
        sub-pixel signals (should span two stripe periods).
    envelope_follow_px : odd narrow window (px, about one stripe period: 9 at the paper rig; 0, or
        not narrower than ``norm_window_px``: off, the default) over which the local min/max
        envelope follows the pattern's brightness (:func:`gbscan.kernels.follow_envelope_row`):
        where both channels' maxima over it stay below the ``norm_window_px`` ones -- a glossy
        highlight, a brighter surface or the lit side of a shading gradient within the wide
        window's reach (~14 px) -- both channels' ranges shrink by one common factor, so the
        stripes beside it are no longer normalised dark.  A highlight multiplies the pattern (it
        reflects the projector's own colour), so one factor keeps the colour balance; a stripe
        wider than the window keeps its own colour's maximum, so the factor stays near 1 there.
        Measured 0 -> 9 (``scripts/sweep_decode.py``, twenty-third session): the 48 scenes 83.96 ->
        84.48 % reported (the real face's four frames +2.6 / +11.1 / +4.4 / +6.5 points, heads
        +2-5, the hard preset -1..-5), 0 wrong pixels off depth edges both ways, column RMS 0.094
        both; glossy surfaces (``--gloss 1,30``) 78.40 -> 78.35 % (real face +11..+15, heads +3..+6;
        two glossy multi-object frames -9..-10: a box's two faces made one region whose markers then
        disagree, dropped), 0 wrong; room light 91.99 -> 92.16 %, clean 90.10 -> 90.76 %, 0 wrong
        both.  **Not the default** because it revives marginal pixels of the multi-object scene's
        dim tilted panel, whose contacts with the wall the unwrapping does not always cut: at
        150-160 mm baselines (``--set baselines``) the two unlabelled columns at its silhouette
        become labelled, its rows are no longer parted there, and a strip of its top joins the
        wall's region 8 stripes off (1140 pixels on a wrong stripe, 0 with it off); through a lens
        with 1 px of lateral chromatic aberration a 40-px piece is linked 6 stripes off (30).  The gained pixels' factor
        is 0.75-1 there as on the face: no threshold on it tells them apart.  A narrower min/max
        window everywhere (``norm_window_px`` 9) put pixels on wrong stripes at the paper rig too.
    camera_gamma : the camera's encoding gamma; pixel values are linearised as
        ``255 (v/255)**camera_gamma`` first (1 = linear camera), so that boundary midpoints,
        crosstalk and colour balance are physical (sRGB-like cameras: 2.2).
    dark_level : a pixel whose local (max - min) modulation in both channels is below this
        (linear DN) is dark.
    saturation_level : raw green or blue at or above this (DN) is saturated.
    min_contrast : minimum local (max - min) / max of each channel.
    min_run_separation, min_run_swing : a green or blue run at an end of a row's stretch (the
        border, or a gap the unwrapping does not bridge) is no stripe, and is unlabelled (reason
        "low_contrast"), when no pixel's normalised green and blue (``gn``, ``bn``: between their
        local min and max) differ by ``min_run_separation`` (*faint*), or when against the next
        run inward its own colour swings less than ``min_run_swing`` times the other colour
        (*one-sided*: a green stripe is greener and less blue than the blue one beside it; warm
        light is only less blue); the run it uncovers is tested next, and a cyan run at an end is
        peeled when the next run of more than a pixel behind it is faint (cool light raises both
        channels: no marker) (``kernels.faint_runs_row``; 0 disables a test).  Light without the
        pattern -- room light with a colour cast beside stripes fading out at a projector
        terminator or an attached shadow -- is split into "green" and "blue" by the local
        threshold, and the local windows still see the stripes beside it, so no per-pixel rule
        drops it; the unwrapping counted its runs as stripes, 2-10 projector px off, on pixels the
        projector does not light.  Measured (typical preset with
        warm light 0.05 / 0.15 / 0.25 / 0.4 of the projector's, sphere, head, multi-object and
        step, seeds 0-1: 32 frames; off / 0.3 and 0.1): pixels more than half a stripe off outside
        depth edges 329 / 6, unlit pixels reported on sphere and head 317 / 0; the 48-scene
        sweep 83.65 / 83.76 % reported, wrong unchanged.  The swing test looks only at runs below
        twice ``min_run_separation`` (``kernels.SWING_SEP``) and against a neighbour that is no
        faint run itself (beside a marker the mixed pixels ``X Y C X`` are none); ``min_run_swing``
        0.25 cost the sphere 0.6 points at the typical ambient.  See docs/method.md "Ambient light".
    cyan_level : both normalised channels above this -> cyan marker.
    min_level : a pixel whose normalised green and blue are both below this is dark (the unlit
        side of a shadow or of the pattern's border).
    raw_margin : a pixel whose unblurred normalised green - blue contradicts its (blurred) colour
        class by more than this is ambiguous (colour carried across a horizontal edge by the blur).
    extrapolate : pixels beyond a segment's last boundary get a column up to this many
        stripe widths away (0: only pixels between two boundaries).
    contact_ratio, contact_gap_px : a segment end that touches the next segment of its row (at
        most ``contact_gap_px`` pixels between them) is not extrapolated (``extrapolate``) when the
        boundary spacing jumps across the contact by more than this factor (0: always
        extrapolated): the two rows of stripes meet at a depth edge, and the run the edge cuts may
        carry the other surface's colours
        (mixed pixels, the aliased stripes of a surface seen at grazing incidence, a colour
        camera's demosaicing).  A segment split on one surface keeps its spacing and is
        extrapolated as before (:func:`gbscan.kernels.interpolate_columns`).  On the sweep's
        Bayer (RGGB) scenes (``scripts/sweep_decode.py``) the wrong pixels off depth edges go
        101 -> 18 and on them 225 -> 129; coverage is unchanged (+0.0-0.3 points, moving frames 0
        and 9 +1.8 / +2.4: the welds the extrapolated runs made no longer split their regions).
        ``contact_gap_px`` 1 -> 2: a gap of two unlabelled pixels is a contact too (at a
        silhouette a Bayer camera's demosaicing leaves the object's compressed stripes a run that
        continues the wall's, two pixels from the object's segment): Bayer wrong pixels off depth
        edges 24 -> 19, the full-RGB scenes +0.1 points reported, the blur grid's wrong pixels
        (1, 1.5 ... 3 px) 24 / 1 / 12 / 24 / 9 -> 19 / 0 / 10 / 20 / 9; the Bayer multi-object scans
        (``scripts/coverage_study.py --bayer RGGB``, seeds 1, 2) lose their wall points 304 mm off
        the sphere their pixels see (worst 304 -> 190 / 4.8 mm: the 190 mm one is the wall carried
        a row down onto a box's top); the full-RGB scans do not change.  3 gains nothing more.
    contact_regions : such a contact is not extrapolated either when both segments lie in regions
        the markers indexed and the columns jump across it: the next segment's first boundary
        more than a stripe from this one's last interval continued to it (and the other way
        round).  Two surfaces meet there whose stripes line up an even number of stripes apart
        and with the same width, so the spacing test cannot see it, and the run between the last
        boundaries may be either surface's.  The layouts set at 620 mm with the wall at 763 mm
        (``scripts/sweep_decode.py --set layouts``): at a near object's right silhouette its row
        segment ended one run into the wall, whose stripe there has the object's next colour 12
        stripes on, and that run took the object's columns (3 and 4 wrong pixels off depth
        edges); two 1-px columns beside a silhouette at 800 mm too.  Twenty-ninth session: layouts
        15 -> 6 wrong off depth edges (280 -> 161 on them), 84.09 -> 84.07 % reported; on depth
        edges mirrored 83 -> 38, panels 228 -> 161; reported 48 scenes 85.12 -> 85.12 %, room
        light 92.66 -> 92.67, clean 90.69 -> 90.68, baselines 87.06, mirrored 91.76 -> 91.71,
        panels 89.13 -> 89.11; none wrong off depth edges added (the 48 scenes' on them 46 -> 47).
        The offsets are the indexing's, before the linking, so that every column map of a frame
        sees the same contacts.
    extrapolate_fit : the pixels beyond the end boundary of a segment with at least this many
        located boundaries are extrapolated with the least-squares quadratic of column against
        camera position through the ``extrapolate_fit`` boundaries at that end, not with the end
        interval's straight line (0: always the straight line; see
        :func:`gbscan.kernels.interpolate_columns`).  At a silhouette the stripes widen or narrow
        from one boundary to the next (an end toward the projector widens them): the straight line
        misses that, always the same way, and rests on two located positions alone.  The 5987
        extrapolated pixels of 8 sphere / face / real-face frames (5 vs 0): projector column error
        median 0.27 -> 0.21 px, mean -0.26 -> -0.13 px, 95th percentile 1.12 -> 0.90 px, worst
        2.43 -> 1.78 px, 446 -> 193 over 1 px; a plane's are unchanged (worst 0.31 / 0.30 px).  A
        straight line fitted to 3 or 4 boundaries doubled the errors, 4, 6 and 7 boundaries were
        worse than 5 and a cubic worse than the quadratic (prototype).  ``scripts/sweep_decode.py``
        (48 scenes, all reported non-edge pixels on their right stripe): 3053 -> 1562 more than
        1 px off, column RMS 0.110 -> 0.107 px.  End to end
        (``scripts/coverage_study.py``, seeds 0-2): sphere depth RMS 0.110-0.117 -> 0.101-0.108
        mm, worst 1.83-2.11 -> 1.44-1.56 mm; head 0.214-0.219 -> 0.193-0.201 mm, worst 2.66-3.00
        -> 2.16-2.40 mm, 0.8-1.1 points more kept (fewer points cleaned away); the real face
        turned 30 degrees worst 3.14 -> 1.91 mm (frontal 1.58 -> 2.32 mm); multi-object worst
        2.56-2.91 -> 2.20-2.75 mm at depth RMS +0.002 mm.
    boundary_fit_half : before the columns are interpolated, each boundary's position is replaced
        by the centre value of a quadratic fitted (least squares) to the ``2 h + 1`` consecutive
        boundaries of its segment around it (:func:`fit_boundaries`; 0: the located positions).
        The locator's noise is independent from boundary to boundary while position against
        boundary index is smooth on one surface (the rows are cut at depth edges first).
        Column RMS error of reported non-edge pixels (``scripts/sweep_decode.py`` scenes,
        h = 0 / 3): tilted plane 0.085 / 0.053, step 0.074 / 0.042, multi-object 0.131 / 0.096,
        sphere 0.121 / 0.085, head 0.158 / 0.138, hard plane 0.239 / 0.172, hard sphere
        0.244 / 0.195 projector px; h = 4 and 5 are better on planes only, 2 is worse on these
        scenes (but see ``boundary_fit_alt_half``).
    boundary_fit_alt_half : a second, narrower half window that each indexed region takes
        instead of ``boundary_fit_half`` when it predicts the region's own boundaries better
        (leave-one-out cross-validation, :func:`choose_fit`; 0: every region takes
        ``boundary_fit_half``).  The quadratic over 7 boundaries (~26 camera px) smooths the
        locator's noise, but where the relief changes within it (a real face: cheeks, lips, the
        eyes' surroundings) its bias is the larger error: on the real face (``fran_face``,
        noise-free render) the lowest quarter of the predicted column error was 0.127 projector
        px off with the 7-boundary fit, 0.083 with 5, of which noise 0.024.  The test on the
        region's boundaries sees which of the two dominates: the real face's regions take 5
        boundaries (depth RMS 0.216-0.219 -> 0.18-0.19 mm, seeds 0-2), the plane, the sphere, the
        synthetic head (smooth relief) and the multi-object scene keep 7 (a fixed 5 would raise
        their depth RMS by 55 / 6 / 30 % on the plane / sphere / multi-object scene).
    locking_bins, locking_min_count : the sub-pixel locator's *pixel locking* is taken out of every
        located boundary before the fit (:func:`correct_locking`): its mean error as a function of
        the boundary's sub-pixel phase (``locking_bins`` bins per camera pixel) and of its colours
        (green|blue, blue|green, the marker's), measured on the frame itself from the fit's
        residuals; a type is corrected only when each of its bins holds at least
        ``locking_min_count`` residuals.  ``locking_bins=0``: no correction.  The fit averages
        the locking where the phases in its window differ, but not at a segment's three first and
        last boundaries (kept as located), nor where all boundaries share a phase.  Column RMS of
        ``scripts/sweep_decode.py`` (off / 8 bins): 48 scenes 0.104 / 0.095 projector px (steps
        0.042 -> 0.026-0.028, tilted planes 0.045-0.053 -> 0.032-0.040, multi-object 0.077-0.091 ->
        0.065-0.081, the real face 2-7 % lower), room light 0.077 / 0.070, clean preset 0.107 /
        0.068; no more wrong pixels.  16 and 32 bins measured the same as 8.
    unwrap : parameters of the unwrapping and absolute indexing.
    rim_bias_px : a pixel whose column the along-stripe blur is estimated to pull by more than this
        (projector px; silhouettes above/below slanted stripes, strongly bent stripes) is masked
        "rim" (0: never).  See :func:`rim_rule`.  Measured end to end (typical preset, after
        cleaning; kept % of lit non-edge pixels / depth RMS mm): head 0.4: 83.2/0.278,
        0.55: 84.3/0.298, 0.6: 84.6/0.302, 0.8: 85.8/0.322, 1.2: 86.7/0.351 (and a wrong pixel);
        sphere 0.4: 88.7/0.149, 0.55: 89.3/0.159, 0.8: 90.2/0.183 (2 pixels > half a stripe off).
        With the rim guard and end rows (below) on, the kept pixels are better and 0.7 is the
        default (seeds 0-2, kept % / RMS mm / worst mm): head 0.55: 81.0-81.7/0.25-0.26/2.54,
        0.7: 81.9-82.7/0.26-0.27/2.54, 0.8: 82.2-83.1/0.27-0.28/2.98, 1.0: 82.6-83.6/0.28-0.29/3.47;
        sphere 0.7: 88.3-88.7/0.14/2.14, 1.0: 89.0-89.3/0.16/2.37.
    rim_end_px : pixels at most this far (camera px) from the end of their row's stretch of
        decoded columns, and as close to a dark / saturated / low-contrast pixel or to the image's
        left or right side, are masked "rim" (left/right silhouettes and shadow edges: the local
        min/max windows mix in the background; the frame's sides cut them; 0: never).  2 since
        the blur became automatic: with sigma 1 the pull rule no longer masks the 2nd-3rd pixel
        next to a slanted shadow edge, whose column was up to 1.1 projector px off (3 mm on the
        multi-object scene's wall at 900 mm; 1 -> 2: none left, seeds 0-2).  The sides since
        2026-11-27 (fifteenth session): a wall at 900 mm filling the frame's left side had its
        first columns 0.4-0.9 projector px off, the multi-object scan's worst points (2.75 / 2.69
        / 2.20 -> 1.87 / 2.16 / 1.86 mm, depth RMS 0.193-0.197 -> 0.172-0.176 mm, kept 0.4
        points fewer, seeds 0-2) and through a Bayer camera its points over 3 mm (worst 3.40 /
        2.99 / 3.05 -> 2.39 / 2.47 / 2.26 mm); the 48-scene sweep 84.51 -> 84.23 % reported,
        column RMS 0.107 -> 0.104 projector px.  The columns are still 0.2-0.3 px off on average
        over the next 8 px there (the windows' reach; cause not pinned down: moving the min/max
        windows inside the frame at its sides fixed the normalisation but not the columns).
    rim_end_isolated : the end rule (``rim_end_px``) also masks the last pixel of a row's stretch
        when the next pixel is a striped one that no region holds (a fragment of another surface,
        reported "isolated"): at a silhouette seen through a Bayer camera the demosaicing
        compresses the object's last stripes, and the stretch's end column, extrapolated at the
        surface's pitch, was 5.5 projector px off (7 pixels of the 48-scene sweep, its only wrong
        ones off depth edges).  Measured (twentieth session): the sweep 84.15 -> 83.96 % reported,
        wrong off / on depth edges 7 / 94 -> **0** / 62, columns over 1 px off 1209 -> 1073; room
        light 92.20 -> 91.99 %, the clean preset 90.17 -> 90.10 %, the baselines set 85.74 ->
        85.54 % (0 / 126 -> 0 / 86); scans (``coverage_study.py``, seeds 0-2) kept 0.1-0.3
        points fewer, depth RMS 0.001-0.003 mm lower, the head's worst point (seed 1) 2.27 -> 1.98
        mm.  Both pixels within ``rim_end_px`` (the rule as for pixels without signal) cost the
        sweep 0.53 points and the real face's renders 0.8-1.7.
    rim_end_overflow : the end rule (``rim_end_px``) also masks the last pixel of a row's stretch
        when its colour run goes on for 2 px or more past the columns' reach, in the same region
        (striped, no column yet, so later "no_boundary"): the run is wider than the stripe its
        end was extrapolated over, which is what two surfaces' stripes of one colour look like
        where they meet across a silhouette -- the stretch's last pixel then sits on the other
        surface with this one's column.  Found on the multi-object scene at 700 mm (seeds 0, 1):
        a pixel of a box 92 mm in front of the wall took the wall's column, and the scan kept it
        (its point lies on the wall's plane: nothing in the cloud shows it).  Measured
        (twenty-fifth session; off / on): ``scripts/sweep_decode.py`` 48 scenes 83.96 -> 83.86 %
        reported, wrong on depth edges 62 -> 49, off them 0 -> 0, reported columns over 1 px off
        1073 -> 619; room light 91.99 -> 91.87 %, 19 -> 19, 839 -> 377; clean preset 90.10 ->
        90.01 %, 49 -> 35; baselines 85.54 -> 85.43 %, 86 -> 84; the blur grid 1 / 1.5 / 2 / 2.5 /
        3 px on depth edges 62 / 17 / 26 / 39 / 40 -> 49 / 7 / 12 / 24 / 22 at 0.08-0.12 points
        fewer reported.  Scans (``scripts/coverage_study.py``, seeds 0-2, kept % / depth RMS mm /
        worst mm): sphere 91.9-92.5 -> 91.7-92.2 / 0.086-0.092 -> 0.082-0.088 / 1.31-1.44 ->
        0.90-1.28; head 84.6-86.5 -> 84.1-85.9 / 0.170-0.186 -> 0.163-0.176 / 1.98-2.39 ->
        1.55-1.90; real face 80.7-81.7 -> 80.4-81.4 / 0.179-0.185 -> 0.176-0.182 / 1.77-2.34 ->
        1.53-2.34; multi-object within 0.1 points, worst unchanged.  Masking every stretch end
        next to such a pixel (1 px of overflow enough) cost the sweep 0.27-0.30 points and the
        scans 0.3-1.0.
    rim_end_reach_px : the end rule (``rim_end_px``) at a stretch end next to no signal (or the
        image's side) measures from the stretch's first pixel without signal within its last
        ``rim_end_reach_px`` px, when there is one (a dark pixel there still carries a column
        interpolated across it): from ``rim_end_px`` before that pixel to the end everything is
        masked (0: off).  With the projector on the camera's left, at a forward depth jump whose
        stripes line up in width the far surface's row stretch ran on into the near surface's
        first stripes across a shadow broken into single dark pixels (``GGG . BB . G``): 3-10
        pixels of the multi-object scene at 700 mm 32 projector px off, reported (the mirrored
        set's only wrong pixels off depth edges).  Measured (twenty-seventh session; off / 5):
        ``scripts/sweep_decode.py`` mirrored set 88.88 -> 88.83 % reported, wrong off / on depth
        edges 23 / 106 -> **0** / 83; the 48 scenes 83.86 -> 83.79 %, 0 / 49 -> 0 / 46, columns
        over 1 px off 619 -> 610; room light 91.87 -> 91.85 %, 0 / 19 -> 0 / 19; clean preset
        90.01 -> 89.93 %, 0 / 35 -> 0 / 33; baselines 85.43 -> 85.37 %, 0 / 84 -> 0 / 79.  Scans
        (``scripts/coverage_study.py``, seeds 0-2, kept %): sphere unchanged, head 0.1 points
        fewer, real face 0.2, multi-object 0-0.1; depth RMS and worst points unchanged.  3 and 4
        px leave 2 of the weld's pixels (seed 1); 6 px masks 1.7-2.1 x the pixels 5 does there.
    rim_guard_px : reported pixels at most this many rows above or below a striped pixel the
        decoder could not index (unindexed, isolated) are masked "rim" (0: never; None, the
        default: the blur's sigma rounded, at least 1 -- :func:`guard_rows`).  At a horizontal
        silhouette over a surface the decoder drops, the along-stripe blur carries the reported
        surface's stripes about a sigma onto the dropped one, where they would be triangulated
        on the wrong surface; nothing in the columns shows it.  See :func:`rim_guard`.
    rim_guard_no_boundary : the guard also stands next to pixels masked "no_boundary" (striped
        and in a region, but on a stretch of row too short for two located boundaries: the
        broken-up surface of a silhouette's far side, at grazing incidence or through a Bayer
        camera's demosaicing), not only next to unindexed and isolated ones.  Measured
        (``scripts/sweep_decode.py``, 48 scenes; off / on): wrong pixels on depth edges 189 ->
        95 (full RGB), 145 -> 81 (Bayer), off them 0 -> 0 / 19 -> 13, at 82.36 -> 82.08 / 88.65
        -> 88.42 % reported (real face 74.8 -> 74.0 %).  Scans (``scripts/coverage_study.py``,
        seeds 0-1): sphere kept -0.3/-0.4 points, depth RMS 0.101-0.102 -> 0.099 mm; head -1.0/-0.8
        points, 0.192-0.200 -> 0.181-0.192 mm, worst 2.22 -> 1.93 mm (seed 0); Bayer
        multi-object (seeds 1-2) worst 190 / 4.8 -> 2.99 / 3.05 mm: the wall's stripes carried a
        row down onto a box's top, which the decoder leaves without boundaries.
    join_transitions : report the one-pixel stripe transitions the classifier called dark
        (:func:`gbscan.kernels.join_transitions`): a pixel on a green|blue boundary has about half
        of each colour, and after the local normalisation both can fall under ``min_level`` (most
        of the real face's "dark" pixels: both near 0.33).  The unwrapping already counted such a
        pixel as the transition between its neighbours (its label stays NONE); it is reported when
        both neighbours are reported so far, in one indexed region, after the rim rules, with
        ``gn + bn >= min_level`` and ``min_contrast``.  Relabelling those pixels green or blue in
        the classifier instead (``gn + bn < min_level`` as the dark test) gave the faces about 2
        points but welded a 517-pixel region across a fold beside the real face's nose (turned
        -15 degrees: 3.4 stripes hidden between two camera pixels; the sweep's wrong pixels off
        depth edges 13 -> 529): the dark fold pixels are what parts the two surfaces, so they stay
        dark for the unwrapping.  Measured (``scripts/coverage_study.py``, seeds 0-2; off / on):
        head 84.3-86.3 -> 85.1-87.1 % kept, real face 80.5-81.8 -> 81.6-82.8 %, sphere 92.1-92.6 ->
        92.2-92.7 %, depth RMS +0.000-0.001 mm, worst points and the multi-object scene unchanged
        (2.75 / 2.69 / 2.20 mm); the hard preset, whose noise puts many transitions under
        ``min_level``: sphere 40.5-41.5 -> 48.4-50.6 %, head 4.5-10.3 -> 7.1-12.1 % (its worst point
        on seed 1 1.09 -> 2.61 mm), multi-object 5.2-7.3 -> 6.1-8.6 %; Bayer: head 74.3-74.8 ->
        75.9-76.4 %, sphere and multi-object +0.4-0.7, worst points unchanged.  The 48-scene sweep
        (``scripts/sweep_decode.py``): 83.95 -> 84.47 % reported, wrong pixels off depth edges 13 ->
        13 (at every fixed blur 1 ... 3 px as before), on them 150 -> 159; JPEG q90 4:2:0 off them
        140 -> 146, six more pixels of a region already 8 stripes off.  The joined pixels stay
        edges for the column error model around them (``column_spread``'s sources: the columns
        beside such a pixel are as poor as beside a dropped one); counted as reported there, the
        real face's lowest band of ``sigma_mm`` read 1.92-1.99x the prediction (seeds 0-2; now
        1.84-1.87x, seeds 0-1; without the join 1.81-1.86x; ``scripts/coverage_study.py --sigma``).
        Joined before the rim rules (read as ordinary pixels by the row-end rule too): 84.48 %,
        on depth edges 175 (mixed pixels at silhouettes stopped masking their stretch's end).
    rim_end_rows : reported pixels at most this many rows above or below a pixel without signal
        (dark, saturated, low contrast) or masked "rim" are masked "rim" (0: never; None, the
        default: the blur's sigma rounded, at least 1, as ``rim_guard_px`` -- :func:`guard_end_rows`):
        the top and bottom ends of a surface's stretch along the stripes, where the blur's weights
        are one-sided and the pull rule, which sees only the decoded rows, underestimates the pull
        (head: the end row was up to 2.8 projector px off).  The blur carries stripes about a
        sigma past a silhouette: with the one row used before at every blur, the hard preset's
        multi-object scan (blur 3 px, seed 0) kept a point of the box 231 mm off the wall below it
        that its pixel sees (``scripts/coverage_study.py --preset hard``: now worst 1.48 mm), and
        across fixed blurs 1, 1.25 ... 3 px the sweep's wrong pixels off depth edges went 24 / 5 /
        5 / 15 / 16 / 17 / 34 / 14 / 18 -> 24 / 5 / 1 / 11 / 12 / 13 / 24 / 8 / 9 and on them
        327-647 -> 77-487 (``scripts/sweep_decode.py --blur-grid``).  The cost falls on the frames
        the automatic blur takes above 1.5 px (noisy ones): the hard preset's sweep scenes report
        1-6 points fewer pixels; at the automatic blur no other scene changes.  An end row over
        darkness is kept unless it is dim: ``rim_end_dim_ratio``.
    rim_end_dim_ratio : the ``rim_end_rows`` guard keeps an end row over darkness when it is not
        dim: its phase-blind brightness at least this fraction of the reported pixel
        ``DIM_REF_ROWS`` rows further in (0: every end row masked, the rule before).  Over
        darkness the blur carries nothing but the surface's own stripes; the end rows' error
        (one-sided blur: 0.4-0.55 projector px RMS on the sphere's top and bottom, 0.09 inside)
        is in ``column_sigma``.  What such rows can get badly wrong is the penumbra of a light
        field's or shadow's edge, lit by the optics' defocus alone: on the simulated wall above
        the projected area 0.12-0.19 of the brightness 3 rows in, its columns 0.3-1.1 projector
        px off, a multi-object point 3.03 mm off with the end rows unguarded.  Darkness
        (:func:`rim_guard`): walking on from the end row past the pixels not reported ("rim",
        dropped striped, signal-less ones), two signal-less rows below ``DIM_DARK_RATIO`` of the
        end row's brightness (or one at the image's edge) within ``DIM_WALK_ROWS`` rows, before
        any reported pixel.  A reported pixel first is another surface whose stripes the blur
        may carry, or the same one after a dropout; brightness does not tell them apart safely
        (a mixed silhouette pixel's lies between both surfaces'), so those rows stay masked, as
        do rows in frames with ambient light (no darkness: the hard preset gains nothing); but
        for one case: a single signal-less pixel with a reported one beyond, both as bright as
        the end row within ``DIM_SAME_RATIO``, is a stripe transition the classifier found
        neither green nor blue enough (most of the real face's "dark" pixels).  Measured
        (``scripts/coverage_study.py``, seeds 0-2; 0 / 0.7): sphere 91.7-92.1 -> 92.1-92.6 %
        kept, depth RMS 0.093-0.097 -> 0.097-0.102 mm; head 83.5-85.5 -> 84.3-86.3 %; real face
        80.2-81.5 -> 80.5-81.8 %; multi-object 82.9-85.2 -> 83.1-85.5 %, worst points unchanged
        (2.75 / 2.69 / 2.20 mm); Bayer multi-object +0.2 points, worst unchanged.  The 48-scene
        sweep (``scripts/sweep_decode.py``): 83.75 -> 83.95 % reported, wrong pixels off depth
        edges 13 -> 13, and at every fixed blur 1 ... 3 px as before; on them 147 -> 150 (+3 at
        blurs 1 and 1.25, as before at the others); JPEG q95 4:4:4 29 / 147 -> 29 / 150, q90
        4:2:0 138 / 253 -> 140 / 255.  Also keeping a row whose walk meets a reported pixel as
        bright as itself within 0.7 either way, past any rows, gave the real face 0.4 points
        more, but let 1-3 mixed silhouette pixels of the hard multi-object scene through.
    rim_lit_rows : reported pixels at most this many rows above or below a *lit* pixel the decoder
        could not use -- low contrast (lit, its stripes washed out), isolated (a dropped striped
        scrap) or dark (no modulation; not followed by darkness) -- are masked "rim", with the dim
        test of ``rim_end_dim_ratio`` walking on from that pixel (0: the rule off, those pixels
        then reach as far as ``rim_end_rows`` and ``rim_guard_px`` say; None, the default: one
        row more than the blur's sigma rounded, at least 1 -- :func:`guard_lit_rows`).  At a crease
        the surface goes on, lit, with its stripes slanted: a box's top face seen edge-on above its
        front runs 6 projector px a row, so the blur along the stripes washes its stripes out, and
        its first one or two rows borrow the front face's stripes through the blur: decoded as the
        front's next rows, 4-7 projector px off, smooth with the front face, so the cleaning keeps
        them.  Measured: under room light the multi-object scan's worst point (3x3 supersampled,
        seed 0) cool 0.25 7.71 -> 2.49 mm (10 -> 0 points over 3 mm), warm 0.15 6.14 -> 2.62 mm (4
        -> 0); the sweep's room-light frames 92.72 -> 92.56 % reported, wrong pixels off depth edges
        18 -> 2, on them 135 -> 32; the 48 scenes 84.69 -> 84.51 %, 13 -> 7 and 159 -> 106; clean
        preset 90.48 -> 90.40 %, 0 -> 0, 58 -> 39; kept by the scans (``scripts/coverage_study.py``,
        seeds 0-2) sphere 92.2-92.7 -> 92.0-92.6 %, head 85.1-87.1 -> 84.9-86.9 %, real face
        81.6-82.8 -> 81.4-82.5 %, worst points and depth RMS the same or lower.  Twice the sigma
        instead of one row more (the same at the automatic 1 px blur): at fixed blurs 2 / 3 px the
        sweep's wrong pixels off depth edges 8 / 6 -> 6 / 2, for 0.3-0.5 points of coverage and
        0.2-1.5 points on the hard preset's frames, which had none wrong.  Since 2026-11-27
        (sixteenth session) a pixel the classifier called dark is such a lit pixel too, when no
        darkness follows it (the dim test's walk from it), and a single signal-less row as bright as
        the reported rows on either side is a stripe transition at this reach as at the end rule's:
        the cool room light's last two wrong pixels sat beside a box's top-face pixel called dark.
        Measured: room light 2 -> 0 wrong off depth edges, 31 -> 19 on them, 92.26 -> 92.19 %
        reported; 48 scenes 7 -> 7 (Bayer), 107 -> 90, 84.24 -> 84.03 %; clean 0, 36 -> 31, 90.05 ->
        90.04 %; scans kept (seeds 0-2) sphere 0 to -0.1 points, head -0.1 to -0.2, real face -0.2
        to -0.3, multi-object -0.3 to -0.4, depth RMS and worst points unchanged.
    step_guard_ratio : reported pixels on the dim side of a brightness step inside their region's
        stretch along the stripes, within 3 sigma of the stretch's end, are masked "rim" when the
        bright side is more than this many times brighter (0: never).  See :func:`step_guard`.
        The blur carries a bright surface's stripes across a horizontal depth edge further than
        the guard rows when the surface beyond is dimmer (farther, darker): the hard preset's
        box, 670 mm, over the wall, 900 mm, at a 2.5 px blur: 7 rows, one region, 14 pixels 18
        stripes off (an even shift: the colours agree, only the brightness shows the edge).
        Measured (``scripts/sweep_decode.py``, 48 scenes; off / 1.9): automatic blur 83.26 ->
        83.25 % reported, wrong pixels on depth edges 176 -> 167, off them 13 -> 13 (Bayer);
        across fixed blurs 1, 1.25 ... 3 px off depth edges 13 / 0 / 0 / 9 / 9 / 9 / 16 / 7 / 7 ->
        13 / 0 / 0 / 9 / 9 / 9 / 9 / 7 / 7 (what is left is Bayer scenes'), on them 48-225 ->
        48-223.  Scans (``scripts/coverage_study.py``, seeds 0-2): sphere 0 to -0.1 points kept,
        head -0.1 to -0.3 (its eyebrows: an albedo step near a stretch's end), depth RMS and worst
        points unchanged.  1.6 removed the same wrong pixels and 9 more edge ones, for 0.7-0.8
        points of the head.  Cost 0.3 ms a 640x480 frame
        (0.8 ms on the multi-object scene: one test per column stretch end).
    sandwich_rows : reported runs of one region along a column, at most this many rows long,
        that the surface around them (other regions' runs above and below, within
        ``SANDWICH_GAP_ROWS``) continues to the sub-pixel a whole number of periods away are
        masked "unindexed" (0: never).  See :func:`sandwich_guard`.  The case (the second held-out
        set, ``scripts/sweep_decode.py --set holdout2``, thirtieth session): the multi-object scene
        at 565 mm with its wall at 706 mm, seed 4.  Right of the box the wall's stripes line up
        with the box's 14 stripes on, and 14 rows of a wall strip are welded along their rows into
        the box's region (its 6 markers fit, none of the strip's), between two regions of the wall
        that the strip continues above and below: 217 and 194 pixels 14 stripes off.
    piece_check_px : a piece of an indexed region that the masks leave apart from its body (its
        largest piece of reported pixels joined along rows and columns) is masked "unindexed" when
        at least this many of its pixels contradict their stripe (cyan on a plain stripe, green or
        blue on a marker stripe) and another index of the piece leaves at least this many fewer
        contradicting (0: never).  See :func:`piece_check`.  The case (the third held-out set, ``--set holdout3``,
        thirty-first session): the multi-object scene at 875 mm with its wall at 1 400 mm, which
        is dim; islands of the wall above the big sphere were unwrapped into the sphere's region
        through rows the guards then masked, and took its index: 24 stripes off, 3-30 cyan pixels
        each on plain stripes.  Over the ten sweep sets' 335 frames no piece that is right has
        more than one such pixel.
    piece_alone : such a piece that no reported pixel outside every piece continues (the
        linking's column-continuity votes) is masked "unindexed" too unless its own colours
        favour its index over every other by ``unwrap.min_marker_px`` pixels.  See
        :func:`piece_check`.  Found on the third and fourth held-out sets (thirty-first session):
        over the eleven sweep sets' 367 frames (``piece_check_px`` on), the pieces nothing
        continues held every wrong piece pixel left (3 543: a wall strip 12 stripes off welded to
        a sphere at 890 mm, 2 407) and 18 327 right ones, 17 051 (0.04 % of the 39.5 M reported)
        in pieces no marker of their own fixes; the pieces something continues, 59 wrong pixels
        and 189 457 right.
    piece_linked : a region linked through its neighbours' columns (``unwrap.link_votes``) owes
        its index to them: for ``piece_alone`` its body continues a piece only where reported
        pixels outside every piece continue the body too, and a linked body that a piece masked
        so continued, and nothing else, is checked as a piece after it, by both tests.  The
        case (thirty-third session, the eighth held-out set, ``--set holdout8``, which it
        spent): the multi-object scene at 695 mm with its wall at 1 098 mm.  Below a sphere the
        wall's rows 298-302 were welded onto the sphere's region along its slanted silhouette, 28
        stripes off, its marker (77) landing on the sphere's (49); the guards cut the strip off
        the sphere, but the wall above it, right of the silhouette (650 px, no markers to fix
        it), had been linked through the strip's columns, and each then continued the other:
        2 545 wrong pixels on three frames.  See :func:`piece_check`.
    piece_jump_px : the pieces are also cut where a region's projector column jumps along the
        stripes by more than this many projector px past the along-stripe blur (0: never): a
        line fitted to each side, ``piece_jump_rows`` rows away, and the two not meeting between
        (:func:`gbscan.kernels.jump_flags`; a crease or a curve makes them meet, a depth edge
        does not).  What such a cut leaves apart is tested as a piece (above), and masked with
        the rows the blur mixed where it fails, unless it hangs between two such cuts inside its
        surface (a face's eyelids and lips; :func:`gbscan.kernels.jump_pieces`).  The case
        (thirty-fourth session, the tenth held-out set, ``--set holdout10``, which it spent): the
        multi-object scene at 840 mm with its wall at 1 151 mm.  Below the panel's lower edge a
        pocket of the wall, between an object's silhouette and a shadow, joined the panel's
        region across the edge, 14 stripes off, its one marker (123) landing on the panel's (109):
        the stripes line up but the columns jump 3-4 projector px, blurred over 6 rows; 779-829
        wrong pixels on each of four frames.  ``scripts/sweep_decode.py``, wrong pixels off depth
        edges: that set 5 290 -> 2 072, holdout3 2 181 -> 408, holdout7 291 -> 26, holdout6
        1 699 -> 1 480, holdout4 868 -> 327, holdout5 941 -> 747, layouts 6 -> 0, the others
        unchanged (the eleventh set, made before the rule ran, 20); reported -0.0 to -0.07 points
        over the sets, the real face's renders 0 to -1.8 (where its column falls smoothly 8 px
        over 13 rows, which 4 + 4 rows cannot tell from a blurred jump).  4 rows to the blur and
        2 px fixed the same and cost the faces more.  Cost ~0.35 ms a 640x480 frame.  See
        :func:`piece_check`.
    piece_jump_rows : rows either side of a pixel :func:`gbscan.kernels.jump_flags` leaves to the
        blur before each side's ``JUMP_FIT_ROWS`` fitted rows.
    resample : decode the frame shrunk by this factor (the linear mean over each pixel's area, as a
        camera with larger pixels sees it; ``cv2.INTER_AREA``) and expand the result back to every
        pixel (:func:`decode`).  0, the default: frames whose stripes span more than
        ``RESAMPLE_ABOVE_PX`` camera px (:func:`frame_stripe_px`, from the colour runs) are shrunk
        to about ``RESAMPLE_TO_PX`` per stripe (in steps of ``RESAMPLE_STEP``); 1: never; above 1:
        that factor.  The decoder's pixel-sized rules (windows, gaps, guards, the spacing tests)
        are tuned and validated at the paper's 3.5-4.8 px per stripe; a camera with more pixels
        over the same field of view sees wider stripes, and there they fail: the paper rig with a
        1280x960 camera (7.2-7.7 px per stripe) reported sphere / head / multi-object 80 / 90 /
        76 % of the lit non-edge pixels with 3 / 17 / 67 of them on a wrong stripe, with a
        1920x1440 camera (11 px) 24 / 43 / 7 % with 0 / 0 / 9511 wrong; resampled, 92 / 82 / 83 %
        and 91 / 85 / 83 % with none wrong off depth edges (``scripts/resample_study.py``,
        docs/method.md "Cameras with more pixels"; since then an object before darkness has its
        lit window alone resampled, ``crop``).  Paper-rig frames (at most 4.63 px by the estimate)
        and 10 px stripes are never resampled.
    confidence_spread_px : each reported pixel's confidence is scaled down by its predicted
        column error ``s`` (projector px, :func:`gbscan.kernels.column_spread`: the column's
        roughness along the stripes, its distance to the nearest unreported pixel, and a floor
        that follows the frame's noise, :func:`spread_floor_px`; kept as
        ``StripeMap.column_sigma``):
        ``0.25 + (c - 0.25) / (1 + (s / confidence_spread_px)^2)``, ``c`` the confidence of the
        region's marker margin and the pixel's contrast.  Those two are constant over most of a
        region, so without it the confidence said nothing about the column's accuracy (0: off, the
        confidence as before).  Reported pixels keep at least 0.25, so the cleaning's default
        ``min_confidence`` 0.2 drops none of them; a higher one trades points for accuracy.
        Measured (``scripts/coverage_study.py --confidence``, seeds 0-1): see docs/method.md
        "Per-point confidence".
    crop : decode only the frame's lit window (:func:`lit_window`): the smallest rectangle holding
        every pixel whose green or blue reaches ``dark_level``, grown by twice the classifier's
        reach and ``CROP_REACH_PX``.  Every pixel outside it is dark for the classifier, so the
        result is the same as the whole frame's, bit for bit; the window just skips the passes
        over darkness (an object before a black or distant background: a face, a sphere).  A
        window over ``CROP_MAX_FRACTION`` of the frame is not used, nor one on the staged path
        (``keep_stages``, rotated stripes, a local balance window: :func:`fast_path`).  False:
        always the whole frame.  Measured (interleaved in one process, 640x480, one thread, 2026-11-27): the
        head's window is 26 % of the frame and decodes 1.7-2.0x faster, the real face's 23 %
        and 1.8x, the sphere's 39 % and 1.4-1.5x; the plane (its light fills the frame) and the
        multi-object scene (a wall behind) are decoded whole as before, the window's test costing
        under 0.1 ms (``scripts/bench_decode.py --scene head``).  A lit background (a wall in
        reach of the projector) or a stray bright pixel far from the object (a hot pixel, a
        reflection) widens the window: slower, never different.  A frame decoded shrunk
        (``resample``) has its lit window alone shrunk, decoded and expanded: the decode of the
        window cut out of the frame, its shrunk grid starting at the window's corner, so an
        equally good sampling rather than the same result (``scripts/resample_study.py
        --decode-param crop=false``, seeds 0-1, 1280x960 / 1920x1440: sphere 92.16-92.20 /
        91.90-91.96 % reported against 92.29-92.45 / 91.68-91.84, head 84.40-84.58 / 86.30-86.61
        against 82.29-83.33 / 86.41-86.78, none wrong either way; the 1280x1024 head
        ``bench_decode``: 25.8 -> 13.2 ms).
    subsampled_chroma : what to do with a frame whose colour was stored at half the horizontal
        resolution and converted back to RGB (chroma subsampling: a YUYV or MJPEG camera, JPEG
        4:2:2 / 4:2:0, most video), which :func:`gbscan.chroma.chroma_check` finds in the pixels
        (``stats['chroma']``: its score and verdict).  Such colour edges are two pixels wide, the
        stripes ~3.5: fake cyan appears at green-blue transitions and whole regions are indexed on
        the wrong stripe (``scripts/sweep_decode.py``, 48 scenes, pixels on a wrong stripe off depth
        edges: 0 in full colour; 2039 / 830 through a YUYV / I420 camera as OpenCV converts them,
        ``--yuv``; 352 as JPEG q95 4:2:2, 111 as JPEG q90 4:2:0; scans up to 233 mm off).
        ``"withhold"`` (the default): the frame is decoded, but no pixel is reported -- every pixel
        it would have reported is ``unindexed``, the relative unwrapping (``relative``, ``region``,
        ``column_relative``) is kept, and ``stats['why']`` says why.  A frame decoded shrunk by
        ``SUBSAMPLED_CHROMA_SHRINK`` (2) or more (``resample``: a camera with more pixels than its
        stripes need) is not checked: each decoded pixel averages whole pixel pairs and the
        stripes keep their colours.  ``"decode"``: reported as a full-colour frame would be (wrong
        stripes possible; the check still runs).  ``"off"``: no check (0.9-1.3 ms a frame less).
    lateral_ca, lateral_ca_t, lateral_ca_min_px : measure the lens's lateral chromatic aberration on
        the frame (the blue stripe edges against the green ones, :func:`lateral_chromatic_aberration`)
        and, when it is clear (slope ``lateral_ca_t`` standard errors from 0) and reaches
        ``lateral_ca_min_px`` camera px among the boundaries, move every boundary to its green
        edge (``stats['lateral_ca']``), before the unwrapping's spacing and tilt cuts read them
        (:func:`correct_lateral_ca`).  The sweep through a simulated lens whose blue image is 0.5
        px larger than the green one at the corners (``sim.Conditions.lateral_ca_px``): column RMS
        0.244 projector px uncorrected, 0.107 corrected, 0.094 without aberration; none of the
        sweeps' 189 frames without aberration is corrected (t at most 3.1 where the fit scatters
        under ``CA_MAX_SIGMA_PX``; the hard preset's fits scatter ~1.9 px), so their results are
        the same bit for bit.  0.3-0.4 ms a frame.
    """

    blur_sigma_along_px: float | None = None
    blur_sigma_across_px: float = 0.0
    blur_auto_gain_px: float = 20.0
    blur_auto_min_px: float = 1.0
    blur_auto_max_px: float = 3.0
    stripe_angle_deg: float = 0.0
    balance_window_px: int | None = None
    threshold: str = "local"
    threshold_window_px: int = 15
    norm_window_px: int = 15
    envelope_follow_px: int = 0
    camera_gamma: float = 2.2
    dark_level: float = 2.0
    saturation_level: int = 250
    min_contrast: float = 0.25
    min_run_separation: float = 0.3
    min_run_swing: float = 0.1
    cyan_level: float = 0.6
    min_level: float = 0.35
    raw_margin: float = 0.3
    extrapolate: float = 0.75
    contact_ratio: float = 1.35
    contact_gap_px: int = 2
    contact_regions: bool = True
    extrapolate_fit: int = 5
    boundary_fit_half: int = 3
    boundary_fit_alt_half: int = 2
    locking_bins: int = 8
    locking_min_count: int = 40
    unwrap: UnwrapParams = field(default_factory=UnwrapParams)
    rim_bias_px: float = 0.7
    rim_end_px: int = 2
    rim_end_isolated: bool = True
    rim_end_overflow: bool = True
    rim_end_reach_px: int = 5
    rim_guard_px: int | None = None
    rim_end_rows: int | None = None
    rim_end_dim_ratio: float = 0.7
    rim_lit_rows: int | None = None
    rim_guard_no_boundary: bool = True
    join_transitions: bool = True
    step_guard_ratio: float = 1.9
    sandwich_rows: int = 32
    piece_check_px: int = 3
    piece_alone: bool = True
    piece_linked: bool = True
    piece_jump_px: float = 1.5
    piece_jump_rows: int = 3
    resample: float = 0.0
    confidence_spread_px: float = 0.15
    crop: bool = True
    subsampled_chroma: str = "withhold"
    lateral_ca: bool = True
    lateral_ca_t: float = 5.0
    lateral_ca_min_px: float = 0.1

    def __post_init__(self):
        def bad(name, why):
            raise GBError(f"DecodeParams.{name}: {why}")

        along = self.blur_sigma_along_px
        if along is not None and (isinstance(along, bool) or not isinstance(along, (int, float))
                                  or not 0 <= along <= 50):
            bad("blur_sigma_along_px", f"must be a sigma in [0, 50] px or None (automatic), got {along!r}")
        if not 0 <= self.blur_sigma_across_px <= 50:
            bad("blur_sigma_across_px", f"must be a sigma in [0, 50] px, got {self.blur_sigma_across_px!r}")
        if not 0 <= self.blur_auto_min_px <= self.blur_auto_max_px <= 50 or not self.blur_auto_gain_px > 0:
            bad("blur_auto_*", "need 0 <= blur_auto_min_px <= blur_auto_max_px <= 50 and blur_auto_gain_px > 0, got "
                f"{self.blur_auto_min_px}, {self.blur_auto_max_px}, {self.blur_auto_gain_px}")
        if not math.isfinite(self.stripe_angle_deg) or abs(self.stripe_angle_deg) > 45:
            bad("stripe_angle_deg", f"must be within [-45, 45] degrees of vertical, got {self.stripe_angle_deg}")
        if self.balance_window_px not in (None, 0) and int(self.balance_window_px) < 3:
            bad("balance_window_px", "must be 0/None (whole image) or >= 3")
        if self.threshold not in ("local", "global"):
            bad("threshold", f"must be 'local' or 'global', got {self.threshold!r}")
        if int(self.threshold_window_px) < 3 or int(self.norm_window_px) < 3:
            bad("threshold_window_px/norm_window_px", "must be >= 3")
        if int(self.envelope_follow_px) != 0 and int(self.envelope_follow_px) < 3:
            bad("envelope_follow_px", f"must be 0 (off) or a window of at least 3 px, got {self.envelope_follow_px}")
        if not 0.2 <= float(self.camera_gamma) <= 5:
            bad("camera_gamma", f"must be in [0.2, 5], got {self.camera_gamma}")
        if not 0 <= float(self.min_run_swing) < 1:
            bad("min_run_swing", f"must be in [0, 1) (0 disables the test), got {self.min_run_swing}")
        if not 0 <= float(self.min_run_separation) < 1:
            bad("min_run_separation", f"must be in [0, 1) (0 disables the rule), got {self.min_run_separation}")
        if not 0 <= self.min_contrast < 1 or not 0.5 < self.cyan_level < 1:
            bad("min_contrast/cyan_level", "min_contrast in [0, 1), cyan_level in (0.5, 1)")
        if not (float(self.contact_ratio) == 0.0 or float(self.contact_ratio) > 1.0):
            bad("contact_ratio", f"must be > 1 (a spacing factor) or 0 (disabled), got {self.contact_ratio}")
        cg = self.contact_gap_px
        if isinstance(cg, bool) or not float(cg).is_integer() or not 0 <= int(cg) <= 8:
            bad("contact_gap_px", f"must be a whole number of pixels in [0, 8], got {cg!r}")
        ef = self.extrapolate_fit
        if isinstance(ef, bool) or not float(ef).is_integer() or not (int(ef) == 0 or 3 <= int(ef) <= 15):
            bad("extrapolate_fit", f"must be 0 (straight line) or a number of boundaries in [3, 15], got {ef!r}")
        bf = self.boundary_fit_half
        if isinstance(bf, bool) or not float(bf).is_integer() or not 0 <= int(bf) <= 10:
            bad("boundary_fit_half", f"must be a whole number of boundaries in [0, 10] (0: no fit), got {bf!r}")
        ba = self.boundary_fit_alt_half
        if isinstance(ba, bool) or not float(ba).is_integer() or not (int(ba) == 0 or 2 <= int(ba) <= 10):
            bad("boundary_fit_alt_half", f"must be 0 (every region takes boundary_fit_half) or a whole number "
                                         f"of boundaries in [2, 10], got {ba!r}")
        lb_ = self.locking_bins
        if isinstance(lb_, bool) or not float(lb_).is_integer() or not 0 <= int(lb_) <= 64:
            bad("locking_bins", f"must be a whole number of phase bins in [0, 64] (0: no correction), got {lb_!r}")
        lm = self.locking_min_count
        if isinstance(lm, bool) or not float(lm).is_integer() or int(lm) < 1:
            bad("locking_min_count", f"must be a whole number of boundaries >= 1, got {lm!r}")
        if not isinstance(self.unwrap, UnwrapParams):
            bad("unwrap", "must be an UnwrapParams")
        if not isinstance(self.lateral_ca, bool):
            bad("lateral_ca", f"must be True or False, got {self.lateral_ca!r}")
        if not (float(self.lateral_ca_t) > 0 and float(self.lateral_ca_min_px) >= 0):
            bad("lateral_ca_t/lateral_ca_min_px", f"must be > 0 / >= 0, got {self.lateral_ca_t}, {self.lateral_ca_min_px}")
        if self.subsampled_chroma not in SUBSAMPLED_CHROMA:
            bad("subsampled_chroma", f"must be one of {', '.join(SUBSAMPLED_CHROMA)}, got {self.subsampled_chroma!r}")
        if not (float(self.step_guard_ratio) == 0 or float(self.step_guard_ratio) > 1):
            bad("step_guard_ratio", "must be 0 (off) or a brightness ratio above 1")
        if not (float(self.rim_bias_px) >= 0) or int(self.rim_end_px) < 0:
            bad("rim_bias_px/rim_end_px", "must be >= 0 (0 disables the rule)")
        dr = self.rim_end_dim_ratio
        if isinstance(dr, bool) or not isinstance(dr, (int, float)) or not 0 <= dr <= 1:
            bad("rim_end_dim_ratio", f"must be a brightness ratio in [0, 1] (0: every end row masked), got {dr!r}")
        for name in ("rim_guard_no_boundary", "join_transitions", "crop", "piece_alone", "piece_linked"):
            if not isinstance(getattr(self, name), bool):
                bad(name, f"must be True or False, got {getattr(self, name)!r}")
        pj = self.piece_jump_px
        if isinstance(pj, bool) or not isinstance(pj, (int, float)) or not 0 <= pj < math.inf:
            bad("piece_jump_px", f"must be a column jump in projector px >= 0 (0: never), got {pj!r}")
        pr = self.piece_jump_rows
        if isinstance(pr, bool) or not float(pr).is_integer() or int(pr) < 1:
            bad("piece_jump_rows", f"must be a whole number of rows >= 1, got {pr!r}")
        cs = self.confidence_spread_px
        if isinstance(cs, bool) or not isinstance(cs, (int, float)) or not 0 <= cs < math.inf:
            bad("confidence_spread_px", f"must be a column error in projector px >= 0 (0: off), got {cs!r}")
        rs = self.resample
        if isinstance(rs, bool) or not isinstance(rs, (int, float)) or not (rs == 0 or 1 <= rs <= MAX_RESAMPLE):
            bad("resample", f"must be 0 (automatic), 1 (never) or a shrink factor in (1, {MAX_RESAMPLE}], got {rs!r}")
        for name, unit in (("rim_guard_px", "rows"), ("rim_end_rows", "rows"), ("rim_lit_rows", "rows"),
                           ("sandwich_rows", "rows"), ("piece_check_px", "pixels")):
            v = getattr(self, name)
            if v is None:
                continue
            if isinstance(v, bool) or not float(v).is_integer() or int(v) < 0:
                bad(name, f"must be a whole number of {unit} >= 0 (0 disables the rule), got {v!r}")

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class StripeMap:
    """Decoder output for one frame (H, W = camera image size).

    column : (H, W) float32 continuous projector column (px), NaN where not reported.
    stripe : (H, W) int32 absolute stripe index of the pixel's colour run, -1 where not reported
        (a joined stripe transition, ``DecodeParams.join_transitions``, has no run of its own:
        one of the two stripes it divides; its label stays NONE).
    confidence : (H, W) float32 in [0, 1], 0 where not reported; at least 0.25 where reported.
        How far to trust the pixel: the margin of its region's marker index, its contrast, and
        its predicted column error (``DecodeParams.confidence_spread_px``).
    mask : (H, W) uint8 reason code, 0 = reported (see ``REASONS``).
    relative : (H, W) int32 relative stripe index (consistent within ``region``; also for
        unindexed regions, e.g. with the pure pattern).
    region : (H, W) int32 region id (-1 none).
    column_relative : (H, W) float32 projector column from the *relative* index (correct up to
        one multiple of ``2 * stripe_px`` per region; NaN outside regions).  For the pure pattern
        or priors from elsewhere (e.g. the previous frame).
    labels : (H, W) uint8 colour class (NONE/GREEN/BLUE/CYAN).
    stats : counts per reason, regions found/indexed/dropped, per-stage milliseconds;
        ``decoded_window`` [y0, y1, x0, x1] (half-open, the frame's pixels) the part of the frame
        steps 1-6 ran on (``DecodeParams.crop``; the whole frame when not cropped); resampled,
        the part that was shrunk (``decoded_size`` its size shrunk).
    stages : intermediate images (only when ``decode(..., keep_stages=True)``).
    column_sigma : (H, W) float32 predicted error (one standard deviation, projector px) of each
        reported pixel's ``column``, NaN where not reported (:func:`column_spread`); None when
        ``DecodeParams.confidence_spread_px`` is 0 (the model is not run).  On the simulator the
        columns' actual RMS error is 0.85-1.4 times it over the bulk of the pixels and 0.45-0.65
        times it over the highest few per cent (docs/method.md "Per-point confidence");
        :attr:`gbscan.scan.Scan.sigma_mm` turns it into millimetres along the camera ray.

    A frame decoded resampled (``DecodeParams.resample``) expands ``relative``, ``region``,
    ``labels`` and ``column_relative`` to its pixels when one of them is first read (a scan reads
    none of them), and ``column_sigma`` when it is first read: the same values, computed later
    (:class:`_Deferred`).
    """

    column: np.ndarray
    stripe: np.ndarray
    confidence: np.ndarray
    mask: np.ndarray
    relative: np.ndarray
    region: np.ndarray
    labels: np.ndarray
    stats: dict
    pattern: PatternSpec
    stages: dict | None = None
    column_relative: np.ndarray | None = None
    column_sigma: np.ndarray | None = None

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool, pixels reported (``mask == 0``)."""
        return self.mask == OK

    def arrays(self) -> dict:
        """The arrays and metadata written to ``stripes.npz``."""
        return {
            "column": self.column, "stripe": self.stripe, "confidence": self.confidence, "mask": self.mask,
            "relative": self.relative, "region": self.region, "labels": self.labels,
            **({} if self.column_sigma is None else {"column_sigma": self.column_sigma}),
            "reasons": np.array([f"{k}:{v}" for k, v in REASONS.items()]),
            "pattern": np.array(json.dumps(self.pattern.to_dict())),
            "stats": np.array(json.dumps(self.stats, default=_json_default)),
        }


class _Deferred:
    """Maps of a resampled decode that a scan does not read, expanded to the frame's pixels when a
    StripeMap first reads one of them: ``expand(*args)`` (a function of this module, by name, so
    that a StripeMap pickles) returns them as a dict.  :func:`_expand_maps`: ``relative``,
    ``region``, ``labels``, ``column_relative`` (13 of the 26 bytes a pixel the eight maps take;
    :func:`gbscan.kernels.upsample_maps`, all four at once); :func:`_expand_sigma`:
    ``column_sigma``.  It holds the coarse decode's own arrays, so the result does not depend on
    what is done to the StripeMap's arrays meanwhile (``column_sigma`` is NaN where the expanded
    ``mask`` as decoded reports nothing), and a StripeMap pickles with the small arrays."""

    def __init__(self, args: tuple, expand: str = "_expand_maps"):
        self.args = args
        self.expand = expand
        self.maps: dict | None = None

    def get(self, name: str) -> np.ndarray:
        if self.maps is None:
            self.maps = globals()[self.expand](*self.args)
            self.args = ()
        return self.maps[name]


def _expand_maps(*args) -> dict:
    from . import kernels

    rel, reg, lab, crel = kernels.upsample_maps(*args)
    return {"relative": rel, "region": reg, "labels": lab, "column_relative": crel}


def _expand_sigma(sigma: np.ndarray, reported: np.ndarray) -> dict:
    # the coarse pixel nearest to each full pixel, by the expansion kernels' own rule (their
    # _coarse_columns, for the rows too: _coarse_row is the same mapping), NaN where the expanded
    # map reports nothing: the first-order expansion carries its coarse pixel's error
    from .kernels.resample import _coarse_columns

    h, w = sigma.shape
    H, W = reported.shape
    ys = _coarse_columns(h, H, 0.0)[2]
    xs = _coarse_columns(w, W, 0.0)[2]
    full = np.take(np.take(sigma, ys, axis=0), xs, axis=1)
    full[~reported] = np.nan
    return {"column_sigma": full}


class _DeferredField:
    """A StripeMap field that may hold a :class:`_Deferred`: read, it is replaced by its array."""

    def __init__(self, name: str, default=None):
        self.name, self.default = name, default

    def __get__(self, obj, owner=None):
        if obj is None:
            return self.default
        value = obj.__dict__.get(self.name, self.default)
        if isinstance(value, _Deferred):
            value = obj.__dict__[self.name] = value.get(self.name)
        return value

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.name] = value


# (after the dataclass has taken the fields and column_relative's default from the class)
for _name in ("relative", "region", "labels", "column_relative", "column_sigma"):
    setattr(StripeMap, _name, _DeferredField(_name))
del _name


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


# -- input --------------------------------------------------------------------------------------
def validate_image(image) -> np.ndarray:
    """Check a camera frame; return it as (H, W, 3) uint8 RGB.

    Accepts uint8, uint16 (scaled to 8 bits) and float in [0, 1] (finite).  Raises GBError for
    grey/2-D or non-3-channel images, other dtypes, NaN/inf and images smaller than 8x8.
    """
    if not isinstance(image, np.ndarray):
        raise GBError(f"decode: image must be a numpy array, got {type(image).__name__}")
    if image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 1):
        raise GBError(f"decode: image is grey {image.shape}; the green-blue decoder needs an RGB colour image")
    if image.ndim != 3 or image.shape[2] not in (3, 4):
        raise GBError(f"decode: image must be (H, W, 3) RGB, got shape {image.shape}")
    if image.shape[0] < 8 or image.shape[1] < 8:
        raise GBError(f"decode: image {image.shape[1]}x{image.shape[0]} is too small (need >= 8x8)")
    img = image[:, :, :3]
    if img.dtype == np.uint8:
        return np.ascontiguousarray(img)
    if img.dtype == np.uint16:
        return np.ascontiguousarray((img >> 8).astype(np.uint8))
    if np.issubdtype(img.dtype, np.floating):
        if not np.isfinite(img).all():
            raise GBError("decode: image holds NaN or infinite values; pass a finite image (uint8 RGB preferred)")
        lo, hi = float(img.min()), float(img.max())
        if lo < 0 or hi > 1:
            raise GBError(f"decode: float image values must lie in [0, 1], got [{lo:g}, {hi:g}]; "
                          "pass uint8 RGB or scale to [0, 1]")
        return np.ascontiguousarray(np.round(img * 255.0).astype(np.uint8))
    raise GBError(f"decode: image dtype {img.dtype} is not supported; expected uint8 RGB (or uint16, float in [0, 1])")


def gamma_lut(camera_gamma: float = 2.2) -> np.ndarray:
    """(256,) float32 table: encoded value -> linear ``255 (v/255)**camera_gamma`` (a fresh copy)."""
    return _lut(float(camera_gamma)).copy()


@functools.lru_cache(maxsize=8)
def _lut(camera_gamma: float) -> np.ndarray:
    # gamma_lut's table, made once per gamma for the decoder's kernels (read only by them; the
    # decoder asks for it up to four times a frame, ~50 us each)
    return (255.0 * (np.arange(256) / 255.0) ** float(camera_gamma)).astype(np.float32)


def linearize(image_rgb: np.ndarray, camera_gamma: float = 2.2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB -> linear green, blue (H, W) float32 (0..255 scale) and the raw
    (H, W) uint8 max of green and blue (for the saturation test).  Red is not used."""
    import cv2

    _, g8, b8 = cv2.split(image_rgb)
    lut = gamma_lut(camera_gamma)
    return cv2.LUT(g8, lut), cv2.LUT(b8, lut), cv2.max(g8, b8)


# -- step 1: motion blurring --------------------------------------------------------------------
#: :func:`auto_blur_sigma` samples every SNR_STEP[1]-th pixel of every SNR_STEP[0]-th row
SNR_STEP = (8, 2)
#: automatic resampling (``DecodeParams.resample = 0``): a frame whose stripes span more than
#: ``RESAMPLE_ABOVE_PX`` camera px (at least ``RESAMPLE_MIN_RUNS`` colour runs measured) is shrunk
#: to about ``RESAMPLE_TO_PX`` px per stripe, by at most ``MAX_RESAMPLE`` and to at least
#: ``RESAMPLE_MIN_SIDE_PX`` a side.  The paper rig's frames read 3.5-4.6 px (its 48-frame sweep),
#: with 10 px stripes 4.3-4.8 (validated as they are: docs/method.md "Stripe width"); from twice the
#: paper camera's pixels on, frames decoded as they are put pixels on wrong stripes and resampled
#: none; in between (1.5 x: 5.4-5.8 px) both have a few (``scripts/resample_study.py``)
RESAMPLE_ABOVE_PX = 5.0
RESAMPLE_TO_PX = 3.75
#: the automatic factor is rounded to this step (frames of one sequence get the same factor unless
#: their stripes really change: which regions the markers index can change with it)
RESAMPLE_STEP = 0.25
#: frame_stripe_px: the colour threshold on the balanced (g - b) / (g + b) and the quantile of the
#: run lengths.  On the 48 frames of scripts/sweep_decode.py (3.5-4.6 px per stripe by the truth)
#: 0.84-1.06 x the truth's median, at most 4.63 px (a tilted plane: 4.56); a median at 0.2 reads the
#: hard preset's noisy multi-object frames 1.5 x too wide (weak stripes merge), the markers' G C G
#: runs lift the median (1.09 x on a 1920x1440 frame, 1.02 x at 0.4)
RUN_LEVEL = 0.1
RUN_QUANTILE = 0.4
#: ... over about this many rows (every ``H // RUN_ROWS``-th): on the sweep's frames at least 699
#: runs (a face), estimates within 0.05 px of 120 rows' (0.18 on a hard-preset head), 0.11 against
#: 0.16 ms at 640x480
RUN_ROWS = 80
RESAMPLE_MIN_RUNS = 200
MAX_RESAMPLE = 8.0
RESAMPLE_MIN_SIDE_PX = 32
#: the sigma used when a frame has too few lit samples to measure its SNR
FALLBACK_SIGMA_PX = 2.0


def _sigma_along(params: DecodeParams) -> float:
    """``params.blur_sigma_along_px``; for automatic params not resolved against a frame (the
    rules' direct callers), ``FALLBACK_SIGMA_PX``.  :func:`decode` resolves it per frame."""
    s = params.blur_sigma_along_px
    return FALLBACK_SIGMA_PX if s is None else float(s)


def auto_blur_sigma(image_rgb: np.ndarray, params: DecodeParams = DecodeParams()) -> tuple[float, float]:
    """The along-stripe blur sigma (camera px) for this frame and its stripe SNR.

    image_rgb : (H, W, 3) uint8 RGB.  The SNR is the stripe modulation over the noise of ``g - b``
    in linear DN (:func:`gbscan.kernels.stripe_snr` on a ``SNR_STEP`` grid of the pixels with some
    light, ~0.1 ms at 640x480).  The sigma is ``blur_auto_gain_px / SNR`` clipped to
    ``[blur_auto_min_px, blur_auto_max_px]`` and rounded to 0.25 px, so that frames of one
    sequence get the same sigma unless their conditions really differ.  Fewer than 500 lit
    samples: ``FALLBACK_SIGMA_PX`` and SNR 0.
    """
    snr = frame_snr(image_rgb, params)
    if snr <= 0:
        return FALLBACK_SIGMA_PX, 0.0
    sigma = min(max(params.blur_auto_gain_px / snr, params.blur_auto_min_px), params.blur_auto_max_px)
    return round(4.0 * sigma) / 4.0, snr


def frame_snr(image_rgb: np.ndarray, params: DecodeParams = DecodeParams()) -> float:
    """The frame's stripe SNR (see :func:`auto_blur_sigma`); 0.0 with fewer than 500 lit samples."""
    from . import kernels

    lut = _lut(float(params.camera_gamma))
    noise, mod, n = kernels.stripe_snr(image_rgb, lut, SNR_STEP[0], SNR_STEP[1], float(max(4.0 * params.dark_level, 1.0)))
    if n < 500 or mod <= 0:
        return 0.0
    return float(mod) / max(float(noise), 0.05)


def frame_stripe_px(image_rgb: np.ndarray, params: DecodeParams = DecodeParams()) -> tuple[float, int]:
    """Camera pixels per stripe of a frame and the colour runs measured (0.0, 0: none), from the
    colour runs of ``RUN_ROWS`` rows (:func:`gbscan.kernels.stripe_run_px`: green/blue by the sign of the
    balanced ``g - b`` with hysteresis, the ``RUN_QUANTILE`` of the runs between two colour
    changes).  No decoding: it chooses the decoder's resampling (``DecodeParams.resample``).
    ~0.1 ms at 640x480, ~0.6 ms at 1920x1440."""
    from . import kernels

    img = validate_image(image_rgb)
    step = max(1, img.shape[0] // RUN_ROWS)
    px, n = kernels.stripe_run_px(img, _lut(float(params.camera_gamma)), step, RUN_LEVEL,
                                  float(max(4.0 * params.dark_level, 1.0)), 255, RUN_QUANTILE)
    return float(px), int(n)


def choose_resample(image_rgb: np.ndarray, params: DecodeParams = DecodeParams()) -> tuple[float, float]:
    """The factor :func:`decode` shrinks this frame by (1.0: none) and the frame's camera px per
    stripe (NaN when not measured: a fixed ``params.resample``, or too few colour runs)."""
    if params.resample != 0:
        return float(params.resample), float("nan")
    px, n = frame_stripe_px(image_rgb, params)
    if n < RESAMPLE_MIN_RUNS or not px > RESAMPLE_ABOVE_PX:
        return 1.0, (px if n >= RESAMPLE_MIN_RUNS else float("nan"))
    f = max(round(px / RESAMPLE_TO_PX / RESAMPLE_STEP) * RESAMPLE_STEP, 1.0 + RESAMPLE_STEP)
    f = min(f, MAX_RESAMPLE, min(image_rgb.shape[:2]) / RESAMPLE_MIN_SIDE_PX)
    return max(f, 1.0), px


@functools.lru_cache(maxsize=8)
def _encode_table(camera_gamma: float) -> np.ndarray:
    # (65536,) uint8: the encoded value of linear 255 i / 65535 (the inverse of gamma_lut)
    return np.round(255.0 * (np.arange(65536) / 65535.0) ** (1.0 / float(camera_gamma))).astype(np.uint8)


def resample_size(shape, factor: float) -> tuple[int, int]:
    """(h, w) of an (H, W) frame shrunk by ``factor`` (each side rounded, at least 8)."""
    H, W = int(shape[0]), int(shape[1])
    return max(8, int(round(H / factor))), max(8, int(round(W / factor)))


def shrink_frame(image_rgb: np.ndarray, factor: float, camera_gamma: float = 2.2, red: bool = True) -> np.ndarray:
    """The RGB frame shrunk by ``factor`` (:func:`resample_size`) in linear light: the mean of the
    linearised values over each output pixel's area (``cv2.INTER_AREA``), encoded again with
    ``camera_gamma`` -- what a camera with pixels ``factor`` times larger would record.
    ``red=False`` leaves the red channel 0 (the decoder reads green and blue only)."""
    import cv2

    from . import kernels

    img = validate_image(image_rgb)
    if not 1.0 <= float(factor) <= MAX_RESAMPLE:
        raise GBError(f"shrink_frame: factor must be in [1, {MAX_RESAMPLE:g}], got {factor}")
    h, w = resample_size(img.shape, factor)
    if 2 * h == img.shape[0] and 2 * w == img.shape[1]:   # exactly half: one fused pass, same values
        return kernels.shrink2_rgb(img, _lut(float(camera_gamma)), _encode_table(float(camera_gamma)),
                                   0 if red else 1)
    lin = kernels.linear_rgb(img, _lut(float(camera_gamma)), 0 if red else 1)
    small = cv2.resize(lin, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, lin.shape[2])
    return kernels.encode_rgb(np.ascontiguousarray(small, dtype=np.float32), _encode_table(float(camera_gamma)))


def _shrink_range(stripe_range: np.ndarray, h: int, w: int) -> np.ndarray:
    # the working volume's stripe bounds at the shrunk frame's pixels: the loosest bounds of the
    # full pixels nearest to each (NaN: none); bounds vary slowly, a one-pixel shift is harmless
    H, W = stripe_range.shape[1:]
    ys = np.minimum(((np.arange(h) + 0.5) * H / h).astype(np.int64), H - 1)
    xs = np.minimum(((np.arange(w) + 0.5) * W / w).astype(np.int64), W - 1)
    # (np.take along each axis: 0.8 ms at 1280x1024 -> 731x585, against 2.3-3.0 for the same
    # gather by fancy indexing)
    return np.ascontiguousarray(np.take(np.take(stripe_range, ys, axis=1), xs, axis=2), dtype=np.float32)


def _decode_resampled(img, factor: float, stripe_px_frame: float, pattern: PatternSpec, params: DecodeParams,
                      keep_stages: bool, stripe_range, memo: "StreamMemo | None" = None) -> "StripeMap":
    # decode() of the frame shrunk by ``factor``, expanded back to every pixel (DecodeParams.resample);
    # with ``DecodeParams.crop`` only the lit window is shrunk, decoded and expanded (outside it the
    # frame is dark; the shrunk grid then starts at the window's corner)
    from . import kernels

    t0 = time.perf_counter()
    shape = img.shape[:2]
    window = None
    if params.crop and fast_path(params, keep_stages):
        # the reach with the largest blur the shrunk frame may get
        sigma = params.blur_sigma_along_px if params.blur_sigma_along_px is not None else params.blur_auto_max_px
        window = lit_window(img, params, _gauss_half(float(sigma)).size - 1, _threshold_window(params),
                            int(params.norm_window_px) | 1, scale=float(factor))
    if window is not None:
        img, stripe_range = _cut(window, img, stripe_range)
    small = shrink_frame(img, factor, params.camera_gamma, red=False)
    h, w = small.shape[:2]
    sr = None if stripe_range is None else _shrink_range(stripe_range, h, w)
    t1 = time.perf_counter()
    # (a window cut out already: the shrunk decode need not look for one again, the same result)
    sm = decode(small, pattern, dataclasses.replace(params, resample=1.0, crop=params.crop and window is None,
                                                    subsampled_chroma="off"),
                keep_stages=keep_stages, stripe_range=sr,
                memo=None if memo is None else _ShrunkMemo(memo, shape, factor, 0 if window is None else window[2],
                                                           img.shape[1] / w))
    t2 = time.perf_counter()
    H, W = img.shape[:2]
    column, stripe, conf, mask, counts = kernels.upsample_stripes(
        H, W, sm.column, sm.stripe, sm.confidence, sm.mask, sm.region, float(pattern.stripe_px), NO_BOUNDARY, RIM)
    crel = sm.column_relative if sm.column_relative is not None else np.full((h, w), np.nan, np.float32)
    # relative, region, labels, column_relative: expanded when first read (a scan never does)
    args = (H, W, sm.column, sm.stripe, sm.mask, sm.relative, sm.region, sm.labels,
            np.ascontiguousarray(crel, dtype=np.float32), float(pattern.stripe_px), NO_BOUNDARY, RIM)
    # column_sigma: the coarse pixel's, expanded when first read (a scan reads it for sigma_mm only)
    sargs = None if sm.column_sigma is None else (sm.column_sigma, mask == OK)
    if window is None:
        later = _Deferred(args)
        sigma = None if sargs is None else _Deferred(sargs, "_expand_sigma")
    else:
        column, stripe, conf, mask = _paste_scan_maps(window, shape, column, stripe, conf, mask, counts)
        later = _Deferred((window, shape, "_expand_maps", args), "_paste_expanded")
        sigma = None if sargs is None else _Deferred((window, shape, "_expand_sigma", sargs), "_paste_expanded")
    t3 = time.perf_counter()
    stats = dict(sm.stats)
    stats.update(_reason_stats(counts[:len(REASONS)]))
    stats["decoded_window"] = _window_stat(window, shape)
    ms = dict(stats.get("ms", {}))
    ms.update(resample=round((t1 - t0) * 1e3, 3), upsample=round((t3 - t2) * 1e3, 3),
              total=round((t3 - t0) * 1e3, 3))
    stats["ms"] = ms
    stats["resample"] = round(float(factor), 3)
    stats["decoded_size"] = [int(w), int(h)]
    if math.isfinite(stripe_px_frame):
        stats["stripe_camera_px"] = round(float(stripe_px_frame), 2)
    return StripeMap(column, stripe, conf, mask, later, later, later, stats, pattern, sm.stages, later, sigma)


def _gauss1d(sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.ones(1, np.float32)
    r = max(1, int(math.ceil(3.0 * sigma)))
    x = np.arange(-r, r + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).astype(np.float32)


@functools.lru_cache(maxsize=32)
def _gauss_half(sigma: float) -> np.ndarray:
    """(r+1,) float32 half of :func:`_gauss1d` (centre first), for ``kernels.gauss_rows`` (made
    once per sigma: read only)."""
    k = _gauss1d(sigma)
    return np.ascontiguousarray(k[k.size // 2:])


@functools.lru_cache(maxsize=32)
def _with_sigma(params: "DecodeParams", sigma: float) -> "DecodeParams":
    # params with the automatic blur's sigma filled in (validated once per params and sigma:
    # the automatic sigma takes a few values; ~70 us a frame otherwise)
    return dataclasses.replace(params, blur_sigma_along_px=sigma)


def motion_kernel(sigma_along_px: float, sigma_across_px: float, angle_deg: float) -> np.ndarray:
    """2-D anisotropic Gaussian kernel (odd square, sums to 1), long axis along the stripes.

    ``angle_deg`` is the stripe direction measured from the image's vertical axis (positive
    = clockwise on screen: the stripe's lower end moves to +u).  ``sigma_across_px = 0`` gives
    a kernel one sample wide across (sampled on the rotated line with bilinear weights).
    """
    a = math.radians(angle_deg)
    along = np.array([math.sin(a), math.cos(a)])   # (du, dv) unit vector along the stripe
    across = np.array([math.cos(a), -math.sin(a)])
    r = max(1, int(math.ceil(3.0 * max(sigma_along_px, sigma_across_px, 0.5))))
    v, u = np.mgrid[-r:r + 1, -r:r + 1].astype(np.float64)
    s_al = (u * along[0] + v * along[1])
    s_ac = (u * across[0] + v * across[1])
    sa = max(sigma_along_px, 1e-6)
    if sigma_across_px > 0:
        k = np.exp(-0.5 * (s_al / sa) ** 2 - 0.5 * (s_ac / sigma_across_px) ** 2)
    else:  # a line: triangle (bilinear) weight across, Gaussian along
        k = np.exp(-0.5 * (s_al / sa) ** 2) * np.clip(1.0 - np.abs(s_ac), 0.0, None)
    return (k / k.sum()).astype(np.float32)


def motion_blur(channels: np.ndarray, sigma_along_px: float = 2.0, sigma_across_px: float = 0.0,
                angle_deg: float = 0.0) -> np.ndarray:
    """Paper step 1, *motion blurring*: Gaussian along the stripe direction.

    channels : (H, W) or (H, W, C) float32.  Vertical stripes without blur across (the default)
    use the compiled vertical Gaussian (``kernels.gauss_image``, the arithmetic of the fast path
    in :func:`decode`); vertical stripes with blur across the separable ``cv2.sepFilter2D``; other
    angles the rotated anisotropic kernel (``cv2.filter2D``).  Borders are reflected
    (``BORDER_REFLECT_101``).  Returns float32 of the same shape.
    """
    import cv2

    from . import kernels

    x = np.ascontiguousarray(channels, dtype=np.float32)
    if sigma_along_px <= 0 and sigma_across_px <= 0:
        return x
    if abs(angle_deg) < 1e-9 and sigma_across_px <= 0:
        kh = _gauss_half(sigma_along_px)
        if x.ndim == 2:
            return kernels.gauss_image(x, kh)
        return np.dstack([kernels.gauss_image(np.ascontiguousarray(x[..., c]), kh) for c in range(x.shape[2])])
    if abs(angle_deg) < 1e-9:
        kx = _gauss1d(sigma_across_px)
        ky = _gauss1d(sigma_along_px)
        return cv2.sepFilter2D(x, cv2.CV_32F, kx, ky, borderType=cv2.BORDER_REFLECT_101)
    k = motion_kernel(sigma_along_px, sigma_across_px, angle_deg)
    return cv2.filter2D(x, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT_101)


# -- step 2: colour balancing -------------------------------------------------------------------
def colour_balance(planes, window_px: int | None = None, floor: float = 0.5) -> list[np.ndarray]:
    """Paper step 2, *colour balancing*: ``c_i = C_i / mean_window(C_i)`` per channel.

    planes : sequence of (H, W) float32 channels (here linear green and blue; red is not used).
    ``window_px`` 0/None: the mean over the whole image's lit pixels (uniform objects); an odd
    int: a local box mean (``cv2.blur``), for objects whose colour varies (faces).  Means below
    ``floor`` (dark windows) are clamped to ``floor`` so shadows do not explode.
    Returns a list of float32 planes, ~1 on average.
    """
    import cv2

    planes = [np.asarray(x, dtype=np.float32) for x in planes]
    if not window_px and len(planes) == 2:
        scales = balance_scales(planes[0], planes[1], floor)
        return [x * s for x, s in zip(planes, scales)]
    if not window_px:
        bright = planes[0]
        for x in planes[1:]:
            bright = cv2.max(bright, x)
        # the means from every 4th pixel in both directions (plenty for a global mean)
        sub = [np.ascontiguousarray(x[::4, ::4]) for x in planes]
        lit = cv2.compare(bright[::4, ::4], 4.0 * floor, cv2.CMP_GT)
        if cv2.countNonZero(lit) < 16:
            lit = None
        return [x * np.float32(1.0 / max(cv2.mean(xs, mask=lit)[0], floor)) for x, xs in zip(planes, sub)]
    w = int(window_px) | 1
    return [x / np.maximum(cv2.blur(x, (w, w), borderType=cv2.BORDER_REFLECT_101), np.float32(floor))
            for x in planes]


def balance_scales(g: np.ndarray, b: np.ndarray, floor: float = 0.5) -> tuple[np.float32, np.float32]:
    """Global colour-balance factors ``1 / mean`` of two (H, W) float32 channels (``floor`` as in
    :func:`colour_balance`): the means over every 4th pixel in both directions (plenty for a
    global mean) that is lit (either channel above ``4 floor``; all of them if fewer than 16 are),
    summed in float64 in row-major order (``kernels.lit_means``; the fast path shares it, on the
    samples ``kernels.balance_samples`` blurs alone: :func:`_sample_scales`)."""
    return _sample_scales(g[::4, ::4], b[::4, ::4], floor)


def _sample_scales(gs: np.ndarray, bs: np.ndarray, floor: float = 0.5) -> tuple[np.float32, np.float32]:
    # balance_scales on its samples (every 4th row and column of the blurred channels)
    from . import kernels

    mg, mb, _ = kernels.lit_means(gs, bs, np.float32(4.0 * floor))
    return np.float32(1.0 / max(mg, floor)), np.float32(1.0 / max(mb, floor))


# -- step 3: thresholding -----------------------------------------------------------------------
@dataclass
class Classified:
    """Result of :func:`classify` (all (H, W)).

    labels : uint8 NONE/GREEN/BLUE/CYAN.  reason : uint8 OK/DARK/SATURATED/LOW_CONTRAST.
    d : float32 (g - b)/(g + b) of the balanced channels.  thr : float32 its threshold.
    (``d`` and ``thr`` are None on :func:`decode`'s fast path, which never stores them whole.)
    gn, bn : float32 channels normalised to [0, 1] between their local min and max (sub-pixel).
    contrast : float32 min over the two channels of (local max - local min) / local max.
    """

    labels: np.ndarray
    reason: np.ndarray
    d: np.ndarray
    thr: np.ndarray
    gn: np.ndarray
    bn: np.ndarray
    contrast: np.ndarray


def local_minmax(x: np.ndarray, window_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal running min and max of (H, W) float32 over ``window_px`` (odd), then smoothed
    by a box of the same width so they vary smoothly across stripes (``BORDER_REPLICATE``; as
    ``cv2.erode``/``cv2.dilate`` then ``cv2.blur`` with a 1 x w kernel, compiled:
    ``kernels.local_minmax_image``)."""
    from . import kernels

    return kernels.local_minmax_image(np.ascontiguousarray(x, dtype=np.float32), int(window_px) | 1)


def local_threshold(d: np.ndarray, window_px: int) -> np.ndarray:
    """The paper's local threshold: the ``window_px`` x ``window_px`` box mean of (H, W) float32
    ``d`` (odd window, ``BORDER_REFLECT_101``; as ``cv2.blur``, compiled: ``kernels.box_image``)."""
    from . import kernels

    return kernels.box_image(np.ascontiguousarray(d, dtype=np.float32), int(window_px) | 1)


def _rule_args(params: DecodeParams) -> tuple:
    # the per-pixel rule parameters of kernels.classify_row, in its order
    return (np.float32(params.cyan_level), np.float32(params.min_level), np.float32(params.raw_margin),
            np.float32(params.min_contrast), np.float32(params.dark_level), int(params.saturation_level))


def _stage3_args(params: DecodeParams) -> tuple:
    # the rule parameters of stage 3's row kernels (kernels.classify_image / classify_frame /
    # stream_frame): the per-pixel ones, then the faint-run rule's (kernels.faint_runs_row)
    return (*_rule_args(params), np.float32(params.min_run_separation), np.float32(params.min_run_swing),
            int(params.unwrap.max_gap_px) + 1, _follow_window(params))


def _follow_window(params: DecodeParams) -> int:
    # the odd narrow window of kernels.follow_envelope_row; 0 (off) unless narrower than the
    # min/max window (no narrower window: nothing to follow)
    n = int(params.envelope_follow_px) | 1 if int(params.envelope_follow_px) > 0 else 0
    return n if n < (int(params.norm_window_px) | 1) else 0


def _threshold_window(params: DecodeParams) -> int:
    return int(params.threshold_window_px) | 1 if params.threshold == "local" else 0


def classify(blurred, balanced, raw, raw_max: np.ndarray, params: DecodeParams) -> Classified:
    """Paper step 3, *thresholding* into green / blue / cyan / none.

    blurred : (g, b) (H, W) float32 linear channels after motion blur.  balanced : the same after
    colour balancing.  raw : (g, b) linear channels before blurring.  raw_max : (H, W)
    uint8 max of the raw encoded green and blue (saturation test).
    Green/blue: ``d = (g - b)/(g + b)`` of the balanced channels against its local box mean
    (:func:`local_threshold`, ``threshold="local"``) or 0 (``"global"``).  Cyan (beyond the paper):
    both channels above ``cyan_level`` of their local range (:func:`local_minmax`).  None:
    saturated; dark (local modulation below ``dark_level``, the pixel far below the local stripe
    level, or a row that is dark before blurring -- vertical blur leaks light into shadowed rows);
    low contrast (a channel's local modulation below ``min_contrast`` of its maximum, or the
    unblurred pixel clearly shows the other colour: blurring along the stripes must not carry a
    colour across a horizontal depth edge or shadow edge onto another surface).
    Whole images, one step after another (``kernels.classify_image``); :func:`decode`'s fast path
    streams the same row arithmetic (``kernels.classify_frame``) and gives bit-identical results.
    """
    from . import kernels

    f32 = [np.ascontiguousarray(x, dtype=np.float32) for x in (*blurred, *balanced, *raw)]
    labels, reason, d, thr, gn, bn, contrast = kernels.classify_image(
        *f32, np.ascontiguousarray(raw_max, dtype=np.uint8), _threshold_window(params),
        int(params.norm_window_px) | 1, *_stage3_args(params))
    return Classified(labels, reason, d, thr, gn, bn, contrast)


# -- sub-pixel boundaries -----------------------------------------------------------------------
def subpixel_boundaries(cls: Classified, segs, ox: int = 0) -> np.ndarray:
    """Sub-pixel camera position ``u`` of every junction (stripe boundary) of ``segs`` (``ox``: the
    frame's column where ``cls``' arrays start, a decoded window; positions are the frame's).

    Crossing of the changing channel(s), normalised between local min and max: ``gn = bn`` for
    green|blue, ``bn = 1/2`` for green|cyan, ``gn = 1/2`` for blue|cyan; linear interpolation
    between the two bracketing samples.  Returns (n_junctions,) float32, NaN where not found.
    """
    from . import kernels

    return kernels.subpixel_junctions(cls.gn, cls.bn, segs.row, segs.j_ua, segs.j_ub, segs.j_la, segs.j_lb, segs.u0,
                                      segs.u1, segs.j_seg, int(ox))


#: lateral_chromatic_aberration: G|B boundaries sampled for the fit (evenly, at most this many)
CA_SAMPLE = 8000
#: ... a green and a blue edge further apart than this (px) are not one boundary's
CA_MAX_EDGE_PX = 2.0
#: ... the fit's robust scatter above this (px): too noisy to correct (the hard preset: ~1.9)
CA_MAX_SIGMA_PX = 1.0
#: ... and the fewest it fits on
CA_MIN_JUNCTIONS = 2000


def _colour_pair_junctions(segs) -> tuple[np.ndarray, np.ndarray]:
    # (n_junctions,) bool: the green|blue and the green|cyan boundaries of segs (either order)
    from .kernels._common import BLUE, CYAN, GREEN

    la, lb = segs.j_la, segs.j_lb
    return (((la == GREEN) & (lb == BLUE)) | ((la == BLUE) & (lb == GREEN)),
            ((la == GREEN) & (lb == CYAN)) | ((la == CYAN) & (lb == GREEN)))


def lateral_chromatic_aberration(cls: Classified, segs, jx: np.ndarray, frame_w: int, params: "DecodeParams",
                                 ox: int = 0) -> tuple[np.ndarray, dict | None, tuple[float, float] | None]:
    """The blue channel's stripe edges against the green one's across the frame, and the boundaries
    corrected to the green channel when the offset is clear (``DecodeParams.lateral_ca``).

    A lens's lateral chromatic aberration magnifies the blue image slightly against the green one
    about the optical centre: every blue edge lies ``delta(x) = a + k x`` camera px from where the
    green one is (``a`` also takes a constant misregistration; the projector's own aberration adds
    to it).  A green|blue boundary (located at ``gn = bn``) then sits ``delta / 2`` off, a
    green|cyan one (``bn = 1/2``) ``delta`` off, a blue|cyan one (``gn = 1/2``) not at all: the
    columns pick up a bias that grows toward the frame's sides and differs by boundary type.  On up
    to ``CA_SAMPLE`` green|blue boundaries this locates the green and the blue edge each on its
    own (``kernels.channel_edge_offsets``: each channel's crossing of 1/2, as a cyan boundary is
    located), fits ``delta`` against ``x`` (``kernels.robust_line``: least squares, trimmed twice at
    3 robust sigmas) and, when the slope is ``lateral_ca_t``
    standard errors from 0, the scatter under ``CA_MAX_SIGMA_PX`` and ``delta`` reaches
    ``lateral_ca_min_px`` somewhere among the boundaries, moves every boundary to its green
    edge: ``jx - delta / 2`` (green|blue), ``jx - delta`` (green|cyan).

    ``jx`` (n_junctions,) float32 frame columns, ``frame_w`` the frame's width.  Returns the
    corrected copy (``jx`` itself when not corrected), the stats (None when too few green|blue
    boundaries: ``a_px``, ``k``, ``edge_px`` (|delta| at the frame's farther side), ``t``,
    ``sigma_px``, ``junctions``, ``corrected``) and the fit ``(a, k)`` when corrected, else None
    (for :func:`correct_lateral_ca` on other segments of the same frame).
    """
    from . import kernels

    gb, _ = _colour_pair_junctions(segs)
    sel = np.flatnonzero(gb & np.isfinite(jx))
    if sel.size < CA_MIN_JUNCTIONS:
        return jx, None, None
    if sel.size > CA_SAMPLE:
        sel = sel[np.linspace(0, sel.size - 1, CA_SAMPLE).astype(np.int64)]
    x, d = kernels.channel_edge_offsets(cls.gn, cls.bn, segs.row, segs.j_ua, segs.j_ub, segs.j_la, segs.u0,
                                        segs.u1, segs.j_seg, sel.astype(np.int64), jx, int(ox), CA_MAX_EDGE_PX)
    if x.size < CA_MIN_JUNCTIONS:
        return jx, None, None
    a, k, sig, n_fit, sd_x = kernels.robust_line(x, d, 2)
    if not np.isfinite(sig):
        return jx, None, None
    se_k = sig / (np.sqrt(n_fit) * max(sd_x, 1e-6))
    t = abs(k) / max(se_k, 1e-12)
    reach = max(abs(a + k * float(x.min())), abs(a + k * float(x.max())))
    corrected = bool(t >= params.lateral_ca_t and sig <= CA_MAX_SIGMA_PX and reach >= params.lateral_ca_min_px)
    st = {"a_px": round(float(a), 4), "k": float(f"{k:.4g}"), "edge_px": round(max(abs(a), abs(a + k * (frame_w - 1))), 3),
          "t": round(float(t), 1), "sigma_px": round(float(sig), 3), "junctions": int(n_fit), "corrected": corrected}
    if not corrected:
        return jx, st, None
    return correct_lateral_ca(segs, jx, a, k), st, (a, k)


def correct_lateral_ca(segs, jx: np.ndarray, a: float, k: float) -> np.ndarray:
    """The boundaries ``jx`` (n_junctions,) float32 frame columns of ``segs`` moved to the green
    channel's edge, the blue one lying ``delta = a + k x`` px from it
    (:func:`lateral_chromatic_aberration`): ``- delta / 2`` for green|blue, ``- delta`` for
    green|cyan, blue|cyan as they are.  Returns a float32 copy."""
    gb, gc = _colour_pair_junctions(segs)
    delta = (a + k * jx.astype(np.float64))
    out = jx.astype(np.float64)
    out[gb] -= 0.5 * delta[gb]
    out[gc] -= delta[gc]
    return out.astype(np.float32)


@functools.lru_cache(maxsize=16)
def _fit_weights(half: int) -> np.ndarray:
    t = np.arange(-half, half + 1, dtype=np.float64)
    w = np.linalg.pinv(np.vander(t, 3, increasing=True))[0]
    w.setflags(write=False)
    return w


def fit_boundaries(j_x: np.ndarray, segs, half: int) -> np.ndarray:
    """Boundary positions ``j_x`` (n_junctions,) float64 camera px (NaN: not located) of the
    segments ``segs``, each replaced by the centre of a quadratic fitted to the ``2 half + 1``
    consecutive boundaries of its segment around it (Savitzky-Golay weights; noise of a located
    position divided by about 1.7 for ``half=3``).  Kept as located where the window leaves the
    segment or holds an unlocated boundary; ``half=0`` returns ``j_x`` unchanged."""
    from . import kernels

    if half <= 0 or j_x.size == 0:
        return j_x
    return kernels.fit_junctions(np.ascontiguousarray(j_x, dtype=np.float64), segs.j0, segs.j1,
                                 _fit_weights(int(half)))


#: a region chooses its boundary fit (:func:`choose_fit`) on at least this many boundaries that both
#: windows fit; smaller regions and segments of no region take the frame's choice
FIT_CHOICE_MIN_BOUNDARIES = 50


def fit_weights_loo(half: int) -> tuple[np.ndarray, float]:
    """The centre weights of the ``2 half + 1``-boundary quadratic fit and the factor that turns a
    residual (located minus fitted) into the leave-one-out residual, 1 / (1 - w_centre): the
    position predicted by the same fit to the other ``2 half`` boundaries, exactly (a linear
    smoother's hat-matrix identity)."""
    w = _fit_weights(int(half))
    return w, 1.0 / (1.0 - float(w[int(half)]))


def choose_fit(j_x: np.ndarray, segs, seg_region: np.ndarray, half: int, alt_half: int
               ) -> tuple[np.ndarray, np.ndarray, bool]:
    """Boundary positions ``j_x`` (n_junctions,) float64 camera px fitted as :func:`fit_boundaries`
    does, each indexed region with the half window ``half`` or ``alt_half``, whichever predicts
    the region's boundaries better.

    The score of a window is the sum of the squared leave-one-out residuals
    (:func:`fit_weights_loo`) over the region's boundaries that both windows fit (a fitted
    position equal to the located one counts as not fitted: it adds nothing to either sum).  A
    leave-one-out residual is the locator's noise plus the window's bias, so the sum estimates
    each window's error up to a constant: the wider window wins where noise dominates, the
    narrower where the relief changes within the wider one.  ``alt_half`` is taken only when it
    scores strictly lower.  Regions with fewer than :data:`FIT_CHOICE_MIN_BOUNDARIES` scored
    boundaries, and segments of no region (``seg_region`` < 0), take the frame's choice (all its
    scored boundaries).  ``seg_region`` (n_segments,) int.

    Returns (positions, (n_regions,) bool: the region took ``alt_half``, the frame's choice).
    ``alt_half`` or ``half`` below 2 (a 3-boundary quadratic passes through its boundaries: no
    leave-one-out prediction), or equal: :func:`fit_boundaries` with ``half``."""
    from . import kernels

    n_reg = int(seg_region.max()) + 1 if seg_region.size else 0
    if half < 2 or alt_half < 2 or alt_half == half or j_x.size == 0:
        return fit_boundaries(j_x, segs, half), np.zeros(n_reg, bool), False
    x = np.ascontiguousarray(j_x, dtype=np.float64)
    fit_h, fit_a = fit_boundaries(x, segs, half), fit_boundaries(x, segs, alt_half)
    k_h, k_a = fit_weights_loo(int(half))[1], fit_weights_loo(int(alt_half))[1]
    seg_bin = np.where(seg_region >= 0, seg_region, n_reg)   # no region: bin n_reg
    count, s_half, s_alt = kernels.fit_choice_sums(x, fit_h, fit_a, segs.j0, segs.j1, seg_bin, k_h, k_a, n_reg + 1)
    frame_alt = bool(s_alt.sum() < s_half.sum())
    alt = np.where(count >= FIT_CHOICE_MIN_BOUNDARIES, s_alt < s_half, frame_alt)
    alt[n_reg] = frame_alt
    if not alt.any():
        return fit_h, alt[:n_reg], frame_alt
    return kernels.take_fit(fit_h, fit_a, segs.j0, segs.j1, alt[seg_bin]), alt[:n_reg], frame_alt


#: the boundary fit's half window that :func:`correct_locking` measures the locking with when the
#: fit itself is off (``boundary_fit_half=0``)
LOCKING_FIT_HALF = 3


def correct_locking(j_x: np.ndarray, segs, half: int, bins: int, min_count: int) -> tuple[np.ndarray, np.ndarray, int]:
    """Boundary positions ``j_x`` (n_junctions,) float64 camera px (NaN: not located) with the
    frame's pixel locking taken out: the sub-pixel locator's error depends on where the boundary
    falls between two pixel centres (linear interpolation of a profile that is not straight over
    a pixel, the local min/max normalisation) and on its colours.

    The locking curve is measured on the frame: the residuals of the boundary fit
    (:func:`fit_boundaries`, ``half`` or :data:`LOCKING_FIT_HALF` when 0) binned by junction type
    and sub-pixel phase (``bins`` per pixel, :func:`gbscan.kernels.locking_table`); each located
    position then has the curve at its type and phase subtracted
    (:func:`gbscan.kernels.apply_locking`).  Returns (corrected positions, (16, bins) curve in
    camera px, number of junction types corrected); ``bins=0`` returns ``j_x`` unchanged."""
    from . import kernels

    if bins <= 0 or j_x.size == 0:
        return j_x, np.zeros((16, 0)), 0
    h = int(half) if half > 0 else LOCKING_FIT_HALF
    fit = fit_boundaries(j_x, segs, h)
    table = np.zeros((16, int(bins)), np.float64)
    n = kernels.locking_table(j_x, fit, segs.j_la, segs.j_lb, segs.j0, segs.j1, h, int(bins), int(min_count), table)
    if n == 0:
        return j_x, table, 0
    return kernels.apply_locking(j_x, segs.j_la, segs.j_lb, table), table, int(n)


def rim_rule(column_rel: np.ndarray, region: np.ndarray, reg_off_px: np.ndarray, reason: np.ndarray,
             params: DecodeParams, pull_out: np.ndarray | None = None, labels: np.ndarray | None = None) -> int:
    """Mask ``RIM`` the columns that silhouettes and bends make unreliable; returns their count.

    column_rel : (H, W) float32 relative projector columns (px, NaN none); region : (H, W) int32;
    reg_off_px : (n_regions,) float32 absolute offset of each region (projector px), NaN if not
    indexed (the rules compare columns across regions).  reason : (H, W) uint8 codes, written in
    place where still OK (:func:`gbscan.kernels.finish_pixels` keeps any input reason).
    pull_out : optional (H, W) float32 that receives the estimated pull (diagnostics, tests).
    Two rules (one pass, :func:`gbscan.kernels.rim_mask`):

    * *pull* (``rim_bias_px``): to first order the decoded column is the true column blurred along
      the stripes like the image, with weights only where the surface gives signal.  On a plane
      that changes nothing; where stripes bend (``c_vv``) or the surface ends above or below a
      slanted stripe (one-sided weights at a silhouette) the column is pulled.  The same blur on
      the *decoded* column estimates that pull (blurring a blurred column moves it by the same
      amount, to first order): a vertical mean over ``2 h + 1`` rows, ``h = round(sqrt(3) sigma)``
      (the variance of the Gaussian), normalised over the finite columns; pixels pulled by more
      than ``rim_bias_px`` are masked.  Modelled for vertical stripes (``stripe_angle_deg == 0``)
      only.  Subtracting the pull instead of masking was measured: it raises the depth RMS of the
      kept pixels on sphere and head.
    * *end* (``rim_end_px``): pixels at most ``rim_end_px`` from the end of their row's stretch of
      columns and as close to a pixel without signal (dark, saturated, low contrast) or to the
      image's left or right side: left/right silhouettes and shadow edges, where the local
      min/max windows mix in the background, and the frame's sides, which cut them; with
      ``rim_end_isolated`` also a stretch's last pixel whose next pixel is striped but in no
      region (a fragment of another surface beyond a silhouette), with ``rim_end_overflow`` one
      whose colour run goes on for 2 px or more without a column (``labels``, the classifier's
      (H, W) colours; the rule is off without them).
      With ``rim_end_reach_px`` the end of a stretch that ends next to no signal is its first
      pixel without signal within its last ``rim_end_reach_px`` px, when there is one (single dark
      pixels carry interpolated columns: a far surface's stretch running on into a near one's
      first stripes across a shadow broken up by them).
    """
    from . import kernels

    sigma = _sigma_along(params)
    modelled = sigma > 0 and abs(params.stripe_angle_deg) < 1e-9
    pull = float(params.rim_bias_px) if modelled else 0.0
    half = max(1, int(round(math.sqrt(3.0) * sigma)))
    if pull_out is None:
        pull_out = np.zeros((0, 0), np.float32)
    return int(kernels.rim_mask(np.ascontiguousarray(column_rel, dtype=np.float32),
                                np.ascontiguousarray(region, dtype=np.int32),
                                np.ascontiguousarray(reg_off_px, dtype=np.float32), reason, half, pull,
                                int(params.rim_end_px), RIM, pull_out, bool(params.rim_end_isolated),
                                bool(params.rim_end_overflow) and labels is not None,
                                np.zeros((0, 0), np.uint8) if labels is None else np.ascontiguousarray(labels),
                                int(params.rim_end_reach_px)))


def _rows_or_sigma(rows: int | None, params: DecodeParams) -> int:
    # a row count as given, or when None the along-stripe blur's sigma rounded (at least 1): how
    # far the blur carries stripes
    return int(rows) if rows is not None else max(1, int(round(_sigma_along(params))))


def guard_rows(params: DecodeParams) -> int:
    """The rows :func:`rim_guard` masks next to a dropped surface: ``rim_guard_px``, or when it is
    None the along-stripe blur's sigma rounded (at least 1): how far the blur carries stripes."""
    return _rows_or_sigma(params.rim_guard_px, params)


def guard_end_rows(params: DecodeParams) -> int:
    """The rows :func:`rim_guard` masks above and below a pixel without signal: ``rim_end_rows``,
    or when it is None the along-stripe blur's sigma rounded (at least 1), as :func:`guard_rows`."""
    return _rows_or_sigma(params.rim_end_rows, params)


def guard_lit_rows(params: DecodeParams) -> int:
    """The rows :func:`rim_guard` masks above and below a lit pixel the decoder could not use
    (``LOW_CONTRAST``, ``ISOLATED``, ``DARK`` without darkness beyond): ``rim_lit_rows``, or when
    it is None the along-stripe blur's sigma rounded (at least 1) plus one."""
    if params.rim_lit_rows is not None:
        return int(params.rim_lit_rows)
    return _rows_or_sigma(None, params) + 1


def _unreported(counts: np.ndarray | None, n: int, code: int) -> None:
    # a later mask took n reported pixels to ``code``: move them in the code counts (when given)
    if n and counts is not None:
        counts[OK] -= n
        counts[code] += n


def rim_guard(mask: np.ndarray, column: np.ndarray, stripe: np.ndarray, confidence: np.ndarray,
              rows: int, counts: np.ndarray | None = None, end_rows: int = 0, no_boundary: bool = False,
              image_rgb: np.ndarray | None = None, dim_ratio: float = 0.0, camera_gamma: float = 2.2,
              lit_rows: int = 0) -> int:
    """Mask ``RIM`` the reported pixels within ``rows`` rows (along the stripes) of a pixel whose
    reason is ``UNINDEXED`` or ``ISOLATED`` (or ``NO_BOUNDARY`` with ``no_boundary``), and within
    ``end_rows`` rows of a pixel without signal (``DARK``, ``SATURATED``, ``LOW_CONTRAST``) or
    masked ``RIM``, and within ``lit_rows`` rows of a lit pixel the decoder could not use
    (``LOW_CONTRAST``, ``ISOLATED``, ``DARK``: ``DecodeParams.rim_lit_rows``, a crease; a dark
    one counts only without darkness beyond it, the dim test below); returns their count.

    mask : (H, W) uint8 reason codes; column (H, W) float32, stripe (H, W) int32, confidence
    (H, W) float32: set to NaN / -1 / 0 where masked.  All updated in place, as is ``counts``
    (n_codes,) when given.  Why: the motion blur (paper step 1) runs along the stripes, so at a
    horizontal depth edge it carries each surface's stripes onto the other for about its half
    width.  Where both sides are reported, :func:`rim_rule` sees the pull; where the other side is
    a surface the decoder drops (its index uncertain, or too small), the carried stripes decode
    as a clean continuation of the reported surface, 1-2 rows into the dropped one.

    ``dim_ratio`` > 0 with ``image_rgb`` (H, W, 3) uint8 (the decoded frame; ``camera_gamma`` its
    encoding): a pixel that only a pixel without signal or masked ``RIM`` puts in reach, or a
    lit one within ``lit_rows`` (no unindexed, isolated or no-boundary one within ``rows``), is
    kept when, on each side where one is, darkness follows before any reported pixel -- walking
    from the lit pixel itself when only ``lit_rows`` reaches it -- (two signal-less rows below
    ``DIM_DARK_RATIO`` of its brightness within ``DIM_WALK_ROWS`` rows, past "rim" and dropped
    ones) and it is not dim: its phase-blind brightness at least ``dim_ratio`` times that of the
    reported pixel ``DIM_REF_ROWS`` rows further in.  A penumbra, lit by the optics' defocus alone, is dim and
    its columns are off (see ``DecodeParams.rim_end_dim_ratio``).
    """
    rows, end_rows, lit_rows = int(rows), int(end_rows), int(lit_rows)
    if rows <= 0 and end_rows <= 0 and lit_rows <= 0:
        return 0
    from . import kernels

    ws = getattr(_THREAD, "workspace", None)  # the fast path's scratch when it is large enough
    near = _prefix(ws.near, mask.shape) if ws is not None and ws.near.size >= mask.size else \
        np.empty(mask.shape, np.uint8)
    assert (DARK, SATURATED, LOW_CONTRAST) == (1, 2, 3)  # the kernel's [b_lo, b_hi] range
    dim = float(dim_ratio) if image_rgb is not None and (end_rows > 0 or lit_rows > 0) else 0.0
    if dim > 0:
        if image_rgb.shape != mask.shape + (3,) or image_rgb.dtype != np.uint8:
            raise GBError(f"rim_guard: image_rgb must be uint8 {mask.shape + (3,)} to match mask (the decoded "
                          f"frame), got {image_rgb.dtype} {image_rgb.shape}")
        img, lut = np.ascontiguousarray(image_rgb), _lut(float(camera_gamma))
    else:
        img, lut = np.zeros((0, 0, 3), np.uint8), np.zeros(256, np.float32)
    n = int(kernels.rim_guard_rows(mask, column, stripe, confidence, UNINDEXED, ISOLATED, DARK, LOW_CONTRAST, RIM,
                                   rows if rows > 0 else -1, end_rows if end_rows > 0 else -1, OK, RIM, near,
                                   NO_BOUNDARY if no_boundary else -1, img, lut, STEP_BOX_PX, dim, DIM_REF_ROWS,
                                   DIM_WALK_ROWS, DIM_DARK_RATIO, DIM_SAME_RATIO, LOW_CONTRAST, ISOLATED,
                                   lit_rows if lit_rows > 0 else -1, DARK))
    _unreported(counts, n, RIM)
    return n


#: rim_guard's dim test compares an end pixel with the pixel this many rows further in (beyond a
#: light field's penumbra at the paper's geometry: 0.12-0.19 of the brightness there on the
#: simulated wall at the projected area's top edge)
DIM_REF_ROWS = 3
#: ... and looks this many rows past the end for darkness (the sphere's silhouette: two "rim"
#: rows, two or three dropped grazing rows, then the background)
DIM_WALK_ROWS = 6
#: ... where a signal-less pixel is dark below this fraction of the end pixel's brightness
DIM_DARK_RATIO = 0.5
#: ... and a single signal-less pixel between the end pixel and a reported one, all three within
#: this ratio of brightness either way, is a stripe transition inside the surface, not an edge
#: (on the real face most "dark" pixels inside the lit face: both normalised channels near 0.33,
#: under ``min_level``; the mixed silhouette pixels the rule must not keep differ by 0.71 / 1.44)
DIM_SAME_RATIO = 0.85


#: step_guard's fixed shape: the phase-blind brightness window (camera px, about one green-blue
#: period of 8 px stripes at the paper's geometry), the rows averaged on either side of a step,
#: the flatness (max / min) of the dim side's rows, and the reach in blur sigmas
STEP_BOX_PX, STEP_HALF_ROWS, STEP_FLAT, STEP_REACH_SIGMAS = 7, 2, 1.3, 3.0


#: :func:`column_spread`'s model of a column's error (projector px; fitted on the simulated sphere,
#: head, multi-object scene and plane at 8 px stripes, typical preset: the predicted and the actual
#: error RMS agree within ~1.5x over the middle of the range, the top 3 % is overestimated ~2x):
#: roughness window (rows either side) and scale, the edge term at 1 px along the row and its reach
#: (px), floor.  The floor was 0.04 until the pixel-locking correction (``DecodeParams.locking_bins``,
#: 2026-11-27 sixteenth session) took the smooth surfaces' column error down: with 0.04 the sphere's
#: and the plane's lowest quarter of the prediction then read 0.48 / 0.46x.  With 0.026 and the
#: noise law's excess over it (:func:`spread_floor_px`; seed 0, ``scripts/coverage_study.py
#: --sigma``): plane 0.65x, sphere 0.64x (its SNR 32: floor 0.032), head 1.02x, multi-object 0.74x,
#: the real face 2.1x (1.9x before: its error there is not the locator's).  A floor of 0.02 for
#: every frame: plane 0.82x but head 1.47x and the sphere's middle quarter 1.48x (history.md)
SPREAD_ROUGH_ROWS, SPREAD_ROUGH_SCALE, SPREAD_EDGE_PX, SPREAD_EDGE_CAP, SPREAD_FLOOR_PX = 2, 1.5, 0.2, 6, 0.026
#: the edge term at 1 row along the column (within the same reach).  Smaller than along the row:
#: the roughness, a mean over the second differences the window has, already measures how fast
#: the column bends toward a stretch's top or bottom end, which the end rows miss by.  Measured
#: (scratch, seeds 0-1, typical preset; column error RMS over predicted of the reported lit
#: non-edge pixels one row from an unreported one; the edge term 0.2 both ways with the roughness
#: diluted by its missing rows before): sphere 1.53 / 1.51 -> 0.89 / 0.88, head 1.43 / 1.58 ->
#: 0.95 / 0.97, real face 1.43 / 1.40 -> 0.94 / 0.95, multi-object 0.86 / 0.91 -> 0.75 / 0.82,
#: plane 0.28 / 0.29 -> 0.34 / 0.35; 0 here instead: the multi-object scene's points in the
#: 90-97 % band of ``sigma_mm`` under-predicted 1.21x (``scripts/coverage_study.py --sigma``:
#: 1.07x), its horizontal depth edges' pull, which the roughness does not see
SPREAD_EDGE_ROWS_PX = 0.14
#: the floor grows with the frame's noise (:func:`spread_floor_px`): the noise law is
#: SPREAD_NOISE_PX at this stripe SNR (the typical preset's plane, 36.6, where it was fitted) and
#: blur sigma 1 px, as 1 / SNR and 1 / sqrt(blur) from there
SPREAD_SNR_REF, SPREAD_NOISE_PX = 36.0, 0.04


def spread_floor_px(snr: float, blur_sigma_px: float) -> float:
    """The floor of :func:`column_spread`'s model for a frame of stripe SNR ``snr`` (:func:`frame_snr`)
    decoded with the along-stripe blur ``blur_sigma_px``: the locator's noise on a smooth surface
    grows as 1 / SNR and shrinks as 1 / sqrt(blur) (the Gaussian averages that many rows' worth of
    noise): ``n = SPREAD_NOISE_PX (SPREAD_SNR_REF / snr) / sqrt(max(blur, 1))``; the floor is
    ``sqrt(SPREAD_FLOOR_PX^2 + max(0, n^2 - SPREAD_NOISE_PX^2))``: ``SPREAD_FLOOR_PX`` (what a
    frame's boundaries still miss by at the typical preset's SNR and above) plus, in quadrature,
    what the noise law adds over its value there.

    The law was fitted with one constant, ``max(0.04, n)``, before the pixel-locking correction
    (``DecodeParams.locking_bins``) took the typical preset's smooth-surface error down and left
    the noisy frames' about where it was; the quadrature keeps the hard preset's floor within 5 %
    of the old law's and the typical preset's at the new 0.026.  Measured (seed 0, the column error
    of the lowest quarter of the prediction over its prediction): hard preset plane / sphere /
    head / real face / multi-object 1.92 / 1.53 / 2.28 / 2.17 / 1.64x with a fixed floor, 0.91 /
    0.85 / 1.46 / 1.48 / 0.75x with the noise law (0.86 / 0.86 / 1.30 / 1.45 / 0.68x after the
    locking correction; 1.33 / 1.26 / 1.68 / 1.77 / 1.03x had the whole law been scaled to 0.026);
    typical head 1.32 -> 0.97x, real face 2.41 -> 1.83x.  ``snr`` 0 (unknown): the fixed floor."""
    if not snr > 0:
        return SPREAD_FLOOR_PX
    n = SPREAD_NOISE_PX * (SPREAD_SNR_REF / snr) / math.sqrt(max(blur_sigma_px, 1.0))
    return math.sqrt(SPREAD_FLOOR_PX ** 2 + max(0.0, n * n - SPREAD_NOISE_PX ** 2))
#: the confidence a reported pixel keeps at least (:func:`gbscan.kernels.finish_pixels` and
#: :func:`column_spread` both scale toward it)
CONF_FLOOR = 0.25


_NO_SOURCES = np.zeros(0, np.int64)


def column_spread(mask: np.ndarray, column: np.ndarray, confidence: np.ndarray, params: DecodeParams,
                  want_spread: bool = True, floor_px: float = SPREAD_FLOOR_PX,
                  sources: np.ndarray | None = None) -> np.ndarray | None:
    """Predicted column error (H, W) float32 projector px of the reported pixels (NaN elsewhere;
    None unless ``want_spread``), and their ``confidence`` scaled by it in place
    (``DecodeParams.confidence_spread_px``; see :func:`gbscan.kernels.column_spread` for the
    model; ``floor_px`` its floor, :func:`spread_floor_px`).  mask (H, W) uint8, column (H, W)
    float32, confidence (H, W) float32 as :func:`decode` makes them; ``sources`` (n,) int64
    ascending flat indices of reported pixels the model treats as unreported for its distance
    terms (the joined stripe transitions, :func:`gbscan.kernels.join_transitions`)."""
    from . import kernels

    spread = np.empty(mask.shape if want_spread else (0, 0), np.float32)
    src = _NO_SOURCES if sources is None else np.ascontiguousarray(sources, dtype=np.int64)
    kernels.column_spread(column, mask, confidence, OK, SPREAD_ROUGH_ROWS, SPREAD_ROUGH_SCALE, SPREAD_EDGE_PX,
                          SPREAD_EDGE_CAP, float(floor_px), float(params.confidence_spread_px), CONF_FLOOR, spread,
                          SPREAD_EDGE_ROWS_PX, src)
    return spread if want_spread else None


def step_guard(image_rgb: np.ndarray, mask: np.ndarray, column: np.ndarray, stripe: np.ndarray,
               confidence: np.ndarray, region: np.ndarray, params: DecodeParams,
               counts: np.ndarray | None = None) -> int:
    """Mask ``RIM`` the reported pixels that the along-stripe blur may have given a brighter
    surface's stripes across a horizontal depth edge; returns their count.

    image_rgb : (H, W, 3) uint8 frame; mask (H, W) uint8, column (H, W) float32, stripe (H, W)
    int32, confidence (H, W) float32: updated in place (NaN / -1 / 0 where masked), as is
    ``counts`` (n_codes,) when given; region (H, W) int32.

    Why: the blur (paper step 1) carries each surface's stripes across a horizontal depth edge,
    and where the surface beyond is dimmer (farther, darker, more oblique) its own stripes lose to
    the carried ones for several rows, more than the rows :func:`rim_guard` masks.  The unwrapping
    follows the carried stripes continuously, so those rows join the bright surface's region with
    its index: off by an even number of stripes, colours and markers agreeing.  What shows the
    edge is the *unblurred* brightness: a step along the column inside one region.  A
    phase-blind brightness (linear green + blue over about one period of the row,
    :func:`gbscan.kernels.step_guard`) is compared across each row boundary of a region's stretch
    along a column (``STEP_HALF_ROWS`` rows either side, the two rows at the boundary skipped);
    where one side is
    more than ``params.step_guard_ratio`` times brighter, the dim side is flat (a surface, not the
    ramp of a shadow or of the light field's edge, where carried stripes are the same surface's),
    and the stretch ends on the dim side within ``STEP_REACH_SIGMAS`` blur sigmas, the dim side
    from the step to the stretch's end is masked.  An albedo step on one surface near a stretch's
    end (eyebrows) is masked too: the cost, measured in :class:`DecodeParams`.
    """
    ratio = float(params.step_guard_ratio)
    if ratio <= 0:
        return 0
    from . import kernels

    reach = max(1, int(math.ceil(STEP_REACH_SIGMAS * _sigma_along(params))))
    n = int(kernels.step_guard(np.ascontiguousarray(image_rgb), _lut(float(params.camera_gamma)), STEP_BOX_PX,
                               np.ascontiguousarray(region, dtype=np.int32), mask, column, stripe, confidence,
                               reach, np.float32(ratio), STEP_HALF_ROWS, np.float32(STEP_FLAT), OK, RIM))
    _unreported(counts, n, RIM)
    return n


#: sandwich_guard: the most rows between a run and its neighbour runs, the tolerance (projector px)
#: of the continuations at its ends, and of its rows against the surface around it
SANDWICH_GAP_ROWS = 16
SANDWICH_TOL_PX = 1.0
SANDWICH_LINE_PX = 1.5


def sandwich_guard(mask: np.ndarray, column: np.ndarray, stripe: np.ndarray, confidence: np.ndarray,
                   region: np.ndarray, pattern: PatternSpec, params: DecodeParams,
                   counts: np.ndarray | None = None) -> int:
    """Mask ``UNINDEXED`` the short runs along a column that the surface around them continues a
    whole number of periods away; returns their count.

    mask (H, W) uint8, column (H, W) float32, stripe (H, W) int32, confidence (H, W) float32:
    updated in place (NaN / -1 / 0 where masked), as is ``counts`` (n_codes,) when given; region
    (H, W) int32.

    Why: where a near surface's stripes line up with a far one's (the two an even number of
    stripes apart), the rows that cross a silhouette unparted weld a strip of the far surface into
    the near one's region, and the near one's markers index it.  Seen down a column, the strip is
    a short run of the near surface's region between two runs of the far surface (other regions,
    indexed by their own markers), and it continues them: their columns carried on across the
    rim rows reach it a whole number of periods off, its own carried on reach the run below the
    same number back, and its rows lie on the far surface's line.  A near surface's own short
    run (a thin bar in front of a wall) does that only when its disparity is a whole number of
    periods and the bar is flat and parallel to the wall: then its pixels are dropped, not
    guessed (:func:`gbscan.kernels.sandwich_guard`, ``params.sandwich_rows``).
    """
    rows = int(params.sandwich_rows)
    if rows <= 0:
        return 0
    from . import kernels

    n = int(kernels.sandwich_guard(mask, column, stripe, confidence, np.ascontiguousarray(region, dtype=np.int32),
                                   float(2 * pattern.stripe_px), rows, SANDWICH_GAP_ROWS, SANDWICH_TOL_PX,
                                   SANDWICH_LINE_PX, OK, UNINDEXED))
    _unreported(counts, n, UNINDEXED)
    return n


#: piece_check's jump cut (``DecodeParams.piece_jump_px``): rows fitted on each side, the fewest
#: columns flagged within 4 px for a line, and how far a cut reaches along a longer stretch (px)
JUMP_FIT_ROWS = 4
JUMP_MIN_COLS = 3
JUMP_REACH_PX = 8


def piece_check(mask: np.ndarray, column: np.ndarray, stripe: np.ndarray, confidence: np.ndarray,
                labels: np.ndarray, region: np.ndarray, pattern: PatternSpec, params: DecodeParams,
                counts: np.ndarray | None = None, n_regions: int | None = None,
                linked: np.ndarray | None = None, stats: dict | None = None,
                rim_columns: tuple | None = None) -> tuple[int, int]:
    """Mask ``UNINDEXED`` the pieces of a region cut off from its body whose index nothing but
    the body supports; returns their counts (by their own markers, for nothing continuing them).

    mask (H, W) uint8, column (H, W) float32, stripe (H, W) int32, confidence (H, W) float32:
    updated in place (NaN / -1 / 0 where masked), as is ``counts`` (n_codes,) when given; labels
    (H, W) uint8 colour classes, region (H, W) int32 (ids below ``n_regions``, found when None).

    Why: a region is indexed as a whole, through every pixel the unwrapping joined into it.  The
    rules after it mask some of those pixels (the rim rules, the guards), and where they were
    all that joined a piece of the region to the rest, the piece kept an index it owes to pixels
    the decoder itself rejected.  A piece must then earn its index as a region too small for its
    own does (:func:`gbscan.unwrap.link_components`): by its own markers, or by the columns of
    the reported pixels around it continuing its own.  Two tests, each dropping the piece rather
    than guessing (:func:`gbscan.kernels.piece_check`):

    * its own colours contradict the index -- at least ``params.piece_check_px`` of its pixels
      cyan on a plain stripe or green or blue on a marker stripe -- and another index fits them
      better by as many: a piece of another surface welded on, its markers showing;
    * (``params.piece_alone``) no reported pixel outside every piece continues it (the linking's
      column-continuity votes: two pixels in line above or below one of its pixels, or beside a
      row end past at most ``link_gap_px`` unreported pixels) and its own colours do not favour
      its index over every other by ``min_marker_px`` pixels, one marker's worth: an island
      whose index is the body's word alone.

    ``linked`` (n_regions,) bool, the regions indexed through their neighbours
    (``params.piece_linked``; None: none): the body of such a region continues a piece only
    where reported pixels outside every piece continue the body itself; a linked body nothing
    else continues is tested as a piece after the pieces, where a piece they masked continued it
    (a strip welded onto a region and the surface linked through it may support nothing but
    each other); the other linked bodies are kept, as linked (the pixels that voted for them
    masked by other rules since).

    ``params.piece_jump_px`` > 0: the reported pixels around a line where a region's column jumps
    along the stripes (:func:`gbscan.kernels.jump_flags`, :func:`gbscan.kernels.jump_band`) join
    nothing either.  Two surfaces meeting at a horizontal depth edge weld where their stripes line
    up (an even number of stripes apart) and their markers may land on each other, so nothing in
    the colours parts them; the column still jumps there, by the two surfaces' disparity modulo
    two stripes.  The tests above run with the line's pixels taken out; what they then mask that
    they did not without (:func:`gbscan.kernels.jump_pieces`) is masked, with the line's pixels
    beside it (the rows the blur mixed, "rim"), unless it hangs between two such lines (inside a
    surface: a face's eyelids).  The line's other pixels stay reported.  ``stats``, when given,
    gets ``jump_piece_px`` (pixels so masked) and ``jump_line_px`` (line pixels masked).
    ``rim_columns``: ``(column_rel, reg_shift, reg_indexed)`` of the unwrapping and the indexing
    (:func:`gbscan.kernels.finish_pixels`' inputs), to fit the pixels the rim rules masked too
    (None: the reported pixels only).
    """
    min_px = int(params.piece_check_px)
    fix_px = int(params.unwrap.min_marker_px) if params.piece_alone else 0
    if (min_px <= 0 and fix_px <= 0) or not pattern.markers or mask.size == 0:
        return 0, 0
    from . import kernels

    region = np.ascontiguousarray(region, dtype=np.int32)
    n_reg = int(region.max()) + 1 if n_regions is None else int(n_regions)
    if n_reg <= 0:
        return 0, 0
    vouch = np.ones(n_reg, np.bool_)
    if linked is not None and params.piece_linked:
        vouch[:min(n_reg, linked.size)] = ~linked[:n_reg]
    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    is_marker = np.ascontiguousarray(pattern.is_marker(), dtype=np.bool_)
    gap = int(params.unwrap.link_gap_px)
    n_band = 0
    if float(params.piece_jump_px) > 0:
        k = int(params.piece_jump_rows)
        if rim_columns is None:
            rim_columns = (column, np.zeros(1, np.int64), np.zeros(1, np.bool_))
        col_rel, shift, indexed = rim_columns
        flags, row_n = kernels.jump_flags(mask, column, np.ascontiguousarray(col_rel, dtype=np.float32), region,
                                          np.ascontiguousarray(shift, dtype=np.int64),
                                          np.ascontiguousarray(indexed, dtype=np.bool_), int(pattern.stripe_px), k,
                                          JUMP_FIT_ROWS, float(params.piece_jump_px), OK, RIM)
        if row_n.any():
            band, n_band = kernels.jump_band(mask, region, flags, row_n, JUMP_MIN_COLS, JUMP_REACH_PX, OK)
    if n_band:
        # the tests with the line's pixels taken out, on copies
        m2 = mask.copy()
        m2[band] = RIM
        kernels.piece_check(m2, column.copy(), stripe.copy(), confidence.copy(), labels, region, is_marker, n_reg,
                            min_px, fix_px, gap, OK, UNINDEXED, vouch)
    n_a, n_b = kernels.piece_check(mask, column, stripe, confidence, labels, region, is_marker, n_reg, min_px,
                                   fix_px, gap, OK, UNINDEXED, vouch)
    _unreported(counts, int(n_a) + int(n_b), UNINDEXED)
    n_j = n_jb = 0
    if n_band:
        failed = (m2 == UNINDEXED) & (mask == OK)
        rows = np.flatnonzero(failed.any(axis=1))
        if rows.size:
            # the rows around what the cut lost (its lines within near rows of it)
            near = int(params.piece_jump_rows) + 1
            a, b = max(int(rows[0]) - near - 1, 0), int(rows[-1]) + near + 2
            n_j, n_jb = kernels.jump_pieces(mask[a:b], column[a:b], stripe[a:b], confidence[a:b], failed[a:b],
                                            band[a:b], region[a:b], near, OK, UNINDEXED, RIM)
        _unreported(counts, int(n_j), UNINDEXED)
        _unreported(counts, int(n_jb), RIM)
    if stats is not None:
        stats["jump_piece_px"], stats["jump_line_px"] = int(n_j), int(n_jb)
    return int(n_a), int(n_b)


def _mark_spans(reason: np.ndarray, spans: np.ndarray, code: int) -> None:
    """Set ``code`` on the still-OK pixels of row spans ``(v, u_first, u_last)`` (n, 3) of
    ``reason`` (H, W) uint8, in place (finish_pixels keeps any non-zero input reason)."""
    for v, a, b in spans.tolist():
        row = reason[v, a:b + 1]
        row[row == OK] = code


def _rim_rule_rows(column_rel, region, reg_off_px, reason, done, changed_rows, params: DecodeParams,
                   labels=None) -> np.ndarray:
    """:func:`rim_rule` on ``reason`` where its result ``done`` for other inputs is known: the rule
    at row ``v`` reads rows ``v - h .. v + h`` only (``h`` its half window), so ``done`` (updated
    in place and returned) is recomputed on the rows within ``h`` of ``changed_rows`` (sorted,
    the rows where the inputs differ; repeats allowed), each band with ``h`` rows of context on either side."""
    from . import kernels

    H = reason.shape[0]
    h = max(1, int(round(math.sqrt(3.0) * _sigma_along(params))))
    # the bands of rows within h of a changed row (maximal runs of consecutive rows)
    first, last = kernels.row_bands(np.asarray(changed_rows, dtype=np.int64), h, H)
    for a, b in zip(first.tolist(), last.tolist()):
        lo, hi = max(a - h, 0), min(b + h, H - 1) + 1
        band = reason[lo:hi].copy()
        rim_rule(column_rel[lo:hi], region[lo:hi], reg_off_px, band, params,
                 labels=None if labels is None else labels[lo:hi])
        done[a:b + 1] = band[a - lo:b + 1 - lo]
    return done


def _grow(a: np.ndarray, n: int) -> np.ndarray:
    # ``np.r_[a, np.zeros(n - a.size, np.int64)]`` (the int64 arrays of the regions, extended)
    out = np.zeros(n, np.result_type(a.dtype, np.int64))
    out[:a.size] = a
    return out


def _link_through_neighbours(cls, un, idx, column_all, column_rel, pattern: PatternSpec, params: DecodeParams,
                             memo: dict | None = None) -> int:
    """Index the components the markers cannot index alone through the reported pixels around
    them (:func:`gbscan.unwrap.link_components`); updates ``un`` (region, inconsistent,
    seg_region, stats) and ``idx`` (arrays extended by the new regions) in place and returns the
    new number of regions.  The votes come from pixels that will be reported: indexed, no reason
    so far, consistent, and not pulled by the along-stripe blur (the rim rule on a copy)."""
    from . import kernels
    from . import unwrap as uw

    n_reg = int(idx.indexed.size)
    reg_off = np.where(idx.indexed, idx.offset * pattern.stripe_px, np.nan).astype(np.float32)

    def reported():
        reason = cls.reason.copy()
        if params.rim_bias_px > 0 or params.rim_end_px > 0:
            rim_rule(column_rel, un.region, reg_off, reason, params, labels=cls.labels)
            if memo is not None:
                memo["reason"] = reason  # the decoder reuses it (recomputed only near linked rows)
        return kernels.reported_columns(un.region, reason, un.inconsistent, cls.labels, column_rel, reg_off)

    lk = uw.link_components(cls.labels, un, idx, column_all, reported, pattern, params.unwrap)
    un.stats.update({f"link_{k}": v for k, v in lk.stats.items()})
    if not lk.stats["components_linked"]:
        return n_reg
    segs = un.segments
    changed = lk.seg_region != un.seg_region   # segments given a region (or another one)
    moved = np.flatnonzero(changed).astype(np.int64)
    if _REUSE_LINK_WORK:
        # the region image and the step-7 flags of paint_regions / check_pixels, in place and only
        # where the linking moved segments (their rows and those beside them)
        region, isolated = un.region, un.isolated
        kernels.repaint_segments(segs.seg, segs.row, segs.u0, segs.u1, moved, lk.seg_region.astype(np.int32),
                                 region, isolated)
        near = np.zeros(region.shape[0] + 2, bool)   # near[v + 1]: row v is a moved segment's or beside one
        r = segs.row[moved]
        near[r] = near[r + 1] = near[r + 2] = True
        kernels.check_vertical_rows(np.ascontiguousarray(cls.labels, dtype=np.uint8), un.relative, region,
                                    np.flatnonzero(near[1:-1]).astype(np.int64), un.inconsistent)
        inconsistent = un.inconsistent
    else:
        region, _, isolated = kernels.paint_regions(segs.seg, segs.rel, lk.seg_region.astype(np.int32),
                                                    un.seg_P.astype(np.int32))
        inconsistent = uw.check_pixels(cls.labels, un.relative, region)
    un.region = region
    un.isolated = isolated
    if memo is not None:
        # rows of the segments whose region or region offset the linking changed (the rim rule's
        # inputs differ only there)
        linked_seg = (lk.seg_region >= 0) & lk.linked[np.maximum(lk.seg_region, 0)]
        # (segments are numbered row by row: their rows come sorted; repeats are harmless to
        # _rim_rule_rows, so no np.unique)
        memo["changed_rows"] = segs.row[changed | linked_seg]
    un.seg_region = lk.seg_region
    un.inconsistent = inconsistent
    n_new = int(lk.offset.size)
    ext = n_new - n_reg
    votes = np.maximum(lk.votes + lk.dissent, 1)
    # a linked region's margin: half of a marker-indexed one's, scaled by its vote agreement
    evidence = np.where(lk.linked, 2 * votes, _grow(idx.evidence, n_new))
    mismatch = np.where(lk.linked, 0, _grow(idx.mismatch, n_new))
    runner_up = np.where(lk.linked, lk.votes, _grow(idx.runner_up, n_new))
    idx.offset, idx.indexed = lk.offset, lk.indexed
    idx.evidence, idx.mismatch, idx.runner_up = evidence, mismatch, runner_up
    idx.markers_seen = _grow(idx.markers_seen, n_new)
    if idx.stripe_margin is not None:
        idx.stripe_margin = _grow(idx.stripe_margin, n_new)
    if idx.stripe_strength is not None:
        idx.stripe_strength = _grow(idx.stripe_strength, n_new)
    linked = lk.linked.tolist()
    idx.why = [("linked" if linked[k] else idx.why[k]) for k in range(n_reg)] + ["linked"] * ext
    un.region_px = _grow(un.region_px, n_new)
    un.stats["regions_linked"] = int(lk.linked.sum())
    return n_new


# -- everything ---------------------------------------------------------------------------------
#: decode() reuses the linking's work (every segment's columns, the rim rule on the votes' copy of
#: the reasons) where it is provably the same; False recomputes it as before (tests compare).
_REUSE_LINK_WORK = True


def empty_stripemap(shape, pattern: PatternSpec, reason: int, why: str, stats: dict | None = None) -> StripeMap:
    """A StripeMap reporting nothing, every pixel masked with ``reason``; ``stats['why']`` says why."""
    H, W = shape
    st = dict(stats or {})
    st.update(_count_reasons(np.full((H, W), reason, np.uint8)))
    st["why"] = why
    return StripeMap(np.full((H, W), np.nan, np.float32), np.full((H, W), -1, np.int32),
                     np.zeros((H, W), np.float32), np.full((H, W), reason, np.uint8),
                     np.zeros((H, W), np.int32), np.full((H, W), -1, np.int32), np.zeros((H, W), np.uint8), st,
                     pattern)


def fast_path(params: DecodeParams, keep_stages: bool = False) -> bool:
    """Whether :func:`decode` runs stages 1-3 fused: vertical stripes (``stripe_angle_deg == 0``)
    blurred only along them, the global colour balance, and no stage images requested.  (The
    rotated kernel and the local balance window stay on the staged path: OpenCV's 2-D filters.)"""
    return (not keep_stages and abs(params.stripe_angle_deg) < 1e-9 and params.blur_sigma_across_px <= 0
            and not params.balance_window_px)


class _Workspace:
    """Per-thread scratch of the fast path for one frame size: the classification images that
    never leave :func:`decode` (reason, gn, bn, contrast; the StripeMap copies what it keeps),
    rim_guard's flags, the blurred samples of the colour balance (``kernels.balance_samples``)
    and the row rings of ``kernels.stream_frame`` (the linear and blurred channels never exist as
    whole images).  Reused from frame to frame: fresh pages cost more than the arithmetic here (a
    page fault each 4 KiB).  14 bytes per pixel per decoding thread (+ the rings: about 40 rows)."""

    def __init__(self, H: int, W: int):
        self.shape = (H, W)
        self.gn = np.empty((H, W), np.float32)
        self.bn = np.empty((H, W), np.float32)
        self.contrast = np.empty((H, W), np.float32)
        self.reason = np.empty((H, W), np.uint8)
        self.near = np.empty((H, W), np.uint8)  # rim_guard's flags
        Hs, Ws = -(-H // 4), -(-W // 4)
        self.samples = (np.empty((Hs, Ws), np.float32), np.empty((Hs, Ws), np.float32))
        self._rings: tuple | None = None

    def views(self, h: int, w: int) -> tuple:
        """gn, bn, contrast, reason: (h, w) C-contiguous views of the first ``h * w`` elements of
        the (H, W) scratch (a decoded window, ``DecodeParams.crop``; the arrays themselves for the
        whole frame)."""
        return tuple(_prefix(a, (h, w)) for a in (self.gn, self.bn, self.contrast, self.reason))

    def rings(self, n_linear: int, n_blurred: int, width: int | None = None) -> tuple:
        """The rows of ``kernels.stream_frame``: linear green, blue (float32), raw maximum (uint8),
        blurred green, blue (float32), each (rows, W), at least ``n_linear`` / ``n_blurred`` rows
        (the kernel takes larger rings: one set serves every blur radius and window met so far);
        ``width`` < W: rows of that width (contiguous views of the same memory, a decoded window)."""
        if self._rings is None or self._rings[0].shape[0] < n_linear or self._rings[3].shape[0] < n_blurred:
            W = self.shape[1]
            if self._rings is not None:
                n_linear = max(n_linear, self._rings[0].shape[0])
                n_blurred = max(n_blurred, self._rings[3].shape[0])
            self._rings = (np.empty((n_linear, W), np.float32), np.empty((n_linear, W), np.float32),
                           np.empty((n_linear, W), np.uint8), np.empty((n_blurred, W), np.float32),
                           np.empty((n_blurred, W), np.float32))
        if width is None or width == self.shape[1]:
            return self._rings
        return tuple(_prefix(a, (a.shape[0], int(width))) for a in self._rings)


def _prefix(a: np.ndarray, shape: tuple) -> np.ndarray:
    # the first prod(shape) elements of a C-contiguous array, as a C-contiguous array of that shape
    return a.reshape(-1)[:shape[0] * shape[1]].reshape(shape)


_THREAD = threading.local()


def _workspace(H: int, W: int) -> _Workspace:
    ws = getattr(_THREAD, "workspace", None)
    if ws is None or ws.shape != (H, W):
        ws = _THREAD.workspace = None  # drop the old one first (peak memory)
        ws = _THREAD.workspace = _Workspace(H, W)
    return ws


#: margin (px) of the decoded window (``DecodeParams.crop``) beyond twice the classifier's reach:
#: the reach of the rules after it, which read the pixels and the frame around the striped ones
#: (the rim guard's walk: ``DIM_WALK_ROWS`` + ``DIM_REF_ROWS`` rows and its guard rows, the step
#: guard's ``STEP_BOX_PX`` box, the error model's ``SPREAD_EDGE_CAP`` distances: each under 20 px)
CROP_REACH_PX = 24
#: a lit window over this fraction of the frame is not used (its copies would cost about what the
#: passes over the rest of the frame do)
CROP_MAX_FRACTION = 0.6


def lit_window(image_rgb: np.ndarray, params: DecodeParams, radius: int, thr_w: int,
               norm_w: int, scale: float = 1.0) -> tuple[int, int, int, int] | None:
    """The window of a frame that :func:`decode` classifies and decodes (``DecodeParams.crop``):
    (y0, y1, x0, x1), half-open, or None for the whole frame.

    A pixel is *bright* when its green or blue byte, linearised, reaches ``dark_level``.  The
    classifier reads a pixel's neighbours within ``radius + thr_w // 2`` rows (the blur along the
    stripes, then the threshold window) and ``max(thr_w // 2, 2 (norm_w // 2))`` columns (the
    threshold window; the local min/max and their box mean).  A pixel farther than that from every
    bright pixel sees only linear values under ``dark_level``: its modulation is under it, so it
    is dark and unlabelled, in the frame as in any window around it.  The window is the bright
    pixels' bounding box grown by twice that reach (so the pixels whose neighbourhood the window's
    own border cuts are dark as well) and by ``CROP_REACH_PX`` (what the later rules read around
    striped pixels).  None: no bright pixel, a window over ``CROP_MAX_FRACTION`` of the frame, or a
    ``saturation_level`` a dark pixel could reach (its reason would not be "dark").

    ``scale`` > 1: the window of a frame decoded shrunk by that factor (``DecodeParams.resample``;
    ``radius`` and the windows in the shrunk frame's pixels): the margins plus one shrunk pixel
    (where its grid falls), times ``scale``.  A shrunk pixel is the mean of the frame's pixels it
    covers, so it is bright only if one of them is."""
    from . import kernels

    H, W = image_rgb.shape[:2]
    lut = _lut(float(params.camera_gamma))
    # the first byte whose linear value reaches dark_level (a hair under it: float32 sums of
    # values below it stay below it)
    level = int(np.searchsorted(lut, np.float32(params.dark_level) * np.float32(0.999)))
    if level > 255 or int(params.saturation_level) <= level:
        return None
    y0, y1, x0, x1 = kernels.bright_window(image_rgb, np.uint8(level))
    if y1 == 0:
        return None
    t, h = int(thr_w) // 2, int(norm_w) // 2
    my = 2 * (int(radius) + t) + CROP_REACH_PX
    mx = 2 * max(t, 2 * h) + CROP_REACH_PX
    if scale != 1.0:
        my, mx = int(math.ceil(scale * (my + 1))), int(math.ceil(scale * (mx + 1)))
    y0, y1, x0, x1 = max(0, y0 - my), min(H, y1 + my), max(0, x0 - mx), min(W, x1 + mx)
    if (y1 - y0) * (x1 - x0) > CROP_MAX_FRACTION * H * W:
        return None
    return int(y0), int(y1), int(x0), int(x1)


def _paste(window: tuple, shape: tuple, fill, a: np.ndarray) -> np.ndarray:
    # a window's map (h, w) in a frame-size map filled with ``fill`` (what the whole frame's
    # decode gives its dark pixels)
    from . import kernels

    y0, y1, x0, x1 = window
    if a.shape != (y1 - y0, x1 - x0):
        raise GBError(f"_paste: a {a.shape} map for the window {window}")
    # (np.full, then the window copied: every window pixel written twice; compiled: once)
    return kernels.paste_window(a, int(shape[0]), int(shape[1]), int(y0), int(x0), a.dtype.type(fill))


#: what the whole frame's decode gives a dark pixel, map by map
_DARK_FILL = {"column": np.nan, "stripe": -1, "confidence": 0, "mask": DARK, "relative": 0, "region": -1,
              "labels": 0, "column_relative": np.nan, "column_sigma": np.nan}


def _cut(window: tuple, img: np.ndarray, stripe_range: np.ndarray | None) -> tuple:
    # the frame and the working volume's stripe bounds (2, H, W) or None, cut to a window
    y0, y1, x0, x1 = window
    img = np.ascontiguousarray(img[y0:y1, x0:x1])
    if stripe_range is not None:
        stripe_range = np.ascontiguousarray(stripe_range[:, y0:y1, x0:x1])
    return img, stripe_range


def _paste_scan_maps(window: tuple, shape: tuple, column, stripe, conf, mask, counts: np.ndarray) -> tuple:
    # the four maps a scan reads, from a window back to the frame's pixels; the pixels outside it
    # counted dark in ``counts`` (the reason histogram), in place
    counts[DARK] += shape[0] * shape[1] - mask.size
    return tuple(_paste(window, shape, _DARK_FILL[k], a)
                 for k, a in (("column", column), ("stripe", stripe), ("confidence", conf), ("mask", mask)))


def _window_stat(window: tuple | None, shape: tuple) -> list:
    # stats["decoded_window"]: the window, or the whole frame
    return list(window) if window is not None else [0, shape[0], 0, shape[1]]


def _paste_maps(window: tuple, shape: tuple, relative, region, labels, column_rel) -> dict:
    # the maps of a decoded window that a scan does not read, pasted when first read (_Deferred)
    maps = {"relative": relative, "region": region, "labels": labels, "column_relative": column_rel}
    return {k: _paste(window, shape, _DARK_FILL[k], v) for k, v in maps.items()}


def _paste_expanded(window: tuple, shape: tuple, expand: str, args: tuple) -> dict:
    # the maps of a window decoded shrunk, expanded to the window's pixels (_expand_maps,
    # _expand_sigma) and pasted, when first read (_Deferred)
    return {k: _paste(window, shape, _DARK_FILL[k], v) for k, v in globals()[expand](*args).items()}


def release_workspace() -> None:
    """Free this thread's fast-path workspace (the next :func:`decode` allocates it again)."""
    _THREAD.workspace = None


def cv2_max(a: np.ndarray, b: np.ndarray) -> float:
    """Largest value of two same-shape arrays (OpenCV's fast reductions)."""
    import cv2

    return max(cv2.minMaxLoc(a)[1], cv2.minMaxLoc(b)[1])


def _count_reasons(mask: np.ndarray) -> dict:
    from . import kernels

    return _reason_stats(kernels.count_codes(np.ascontiguousarray(mask, dtype=np.uint8), len(REASONS)))


def _reason_stats(counts: np.ndarray) -> dict:
    # counts[code] of a mask -> the stats entries "pixels", "reported", "reasons"
    return {"pixels": int(counts.sum()), "reported": int(counts[OK]),
            "reasons": {REASONS[k]: int(counts[k]) for k in REASONS}}


def _unwrap_again(cls, un, idx, pattern, params, stripe_range, locate, segments1, **cuts):
    """Unwrap ``cls.labels`` again with more cuts (``cuts``: :func:`gbscan.unwrap.unwrap`'s
    ``retry_px`` / ``sever_px``; ``segments1``: step 1's segments of the first unwrap, reused) and
    index it.  Returns (Unwrapped, RegionIndex, pixels gained) when it indexes more pixels than
    ``un, idx``, else None."""
    from . import unwrap as uw

    p = params.unwrap
    un2 = uw.unwrap(cls.labels, p, locate=locate, segments1=segments1, **cuts)
    idx2 = uw.index_regions(cls.labels, un2.relative, un2.region, int(un2.region_px.size), pattern, p, stripe_range)
    gain = int(un2.region_px[idx2.indexed].sum()) - int(un.region_px[idx.indexed].sum())
    return (un2, idx2, gain) if gain > 0 else None


def _retry_welds(cls, un, idx, pattern, params, stripe_range, locate, segments1=None):
    """Unwrap again with the rows of failed regions also cut at weaker spacing jumps
    (``UnwrapParams.retry_spacing_ratio``), when regions of at least ``retry_min_px`` pixels
    failed with markers that contradict each other (``segments1``: step 1's segments of the
    first unwrap, reused).  Returns the new (Unwrapped, RegionIndex, pixels gained, retry_px)
    when it indexes more pixels, else None."""
    from . import unwrap as uw

    p = params.unwrap
    if p.retry_spacing_ratio <= 0 or not pattern.markers or not len(idx.why):
        return None
    # markers that contradict each other (often a weld of two surfaces)
    failed = uw.failed_regions(idx, un.region_px, p.retry_min_px, (uw.MISFIT, uw.AMBIGUOUS))
    if not failed.any():
        return None
    lut = np.zeros(failed.size + 1, bool)
    lut[:-1] = failed
    retry_px = lut[un.region]            # (region -1 -> the last entry, False)
    again = _unwrap_again(cls, un, idx, pattern, params, stripe_range, locate, segments1, retry_px=retry_px)
    return None if again is None else (*again, retry_px)


def _split_welds(cls, un, idx, pattern, params, stripe_range, locate, segments1=None, retry_px=None):
    """Unwrap again with the vertical links cut at the contact row of every region of at least
    ``retry_min_px`` pixels whose markers do not fit the pattern but fit two offsets above and
    below one row (:func:`gbscan.unwrap.split_row`, ``UnwrapParams.split_rows``); ``retry_px``:
    the cuts of an accepted :func:`_retry_welds`, kept.  Returns the new (Unwrapped, RegionIndex,
    pixels gained) when it indexes more pixels, else None."""
    from . import unwrap as uw

    p = params.unwrap
    if p.split_rows <= 0 or not pattern.markers or not len(idx.why):
        return None
    sever = None
    undecided = []
    for k in np.flatnonzero(uw.failed_regions(idx, un.region_px, p.retry_min_px)):
        got = uw.split_row(cls.labels, un.relative, un.region, int(k), pattern, p, span=True)
        if got is None:
            continue
        v, last = got
        if sever is None:
            sever = np.zeros(un.region.shape, bool)
        sever[v + 1] |= un.region[v + 1] == k
        if last > v and p.split_undecided:
            undecided.append((v + 1, last + 1, un.region[v + 1:last + 1] == k))
    if sever is None:
        return None
    again = _unwrap_again(cls, un, idx, pattern, params, stripe_range, locate, segments1, retry_px=retry_px,
                          sever_px=sever)
    if again is not None and undecided:
        # the rows between the cuts that tie: their surface undecided, reported unindexed
        for a, b, m in undecided:
            r = cls.reason[a:b]
            r[m & (r == OK)] = UNINDEXED
    return again


#: frames a :class:`StreamMemo` reuses a measurement on before measuring it again
STREAM_REMEASURE_EVERY = 16


class StreamMemo:
    """What :func:`decode` measures on a frame that belongs to the camera rather than the scene,
    kept for the next frames of one stream (one camera, one lens setting: a video, a live view;
    :class:`gbscan.scan.Scanner` keeps one; ``gbscan batch`` does not use one, so that a frame's
    outputs do not depend on the frame its worker scanned before):

    * the resampling factor and the frame's camera px per stripe (:func:`choose_resample`:
      the stripes' width in the camera, set by the lens and the working distance), ~0.15-0.2 ms
      a frame;
    * the lens's lateral chromatic aberration, the fit and its stats
      (:func:`lateral_chromatic_aberration`), ~0.2-0.5 ms a frame.

    Each is measured on the first frame, reused on the next ``every - 1`` frames that ask for it,
    then measured again (``every`` 1: every frame, as without a memo).  A measurement is kept
    only when it was made (a frame with too few colour runs or stripe boundaries keeps none, so
    a dark first frame is not a stream's reference) and is keyed by what it depends on: the
    frame's size and the parameters that enter it, so a change of either measures afresh.  On a
    frame that measures, the result is the same as without a memo, bit for bit; on the others it
    differs only by the earlier frame's measurement (the same factor; an aberration fit from
    another frame of the same lens).  The chroma-subsampling check
    (``DecodeParams.subsampled_chroma``) is never kept: it guards against wrong stripes, and
    frames of one folder may come from different files.  ``stats['stream']`` says, per
    quantity, "measured" or "reused" (with the frames since the measurement).  Thread-safe.
    """

    def __init__(self, every: int = STREAM_REMEASURE_EVERY):
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise GBError(f"StreamMemo: every must be an integer >= 1 (frames a measurement is used on), got {every!r}")
        self.every = int(every)
        self._lock = threading.Lock()
        self._kept: dict[str, tuple] = {}    # name -> (key, value, uses so far)

    def get(self, name: str, key):
        """The kept value of ``name`` for ``key`` and the frames since it was measured, counting
        this use; (None, 0) when there is none to reuse (none kept, another key, or used
        ``every`` times: measure and :meth:`put`)."""
        with self._lock:
            kept = self._kept.get(name)
            if kept is None or kept[0] != key or kept[2] >= self.every:
                return None, 0
            self._kept[name] = (kept[0], kept[1], kept[2] + 1)
            return kept[1], kept[2]

    def put(self, name: str, key, value) -> None:
        """Keep ``value`` of ``name`` measured for ``key`` (this frame counts as its first use)."""
        with self._lock:
            self._kept[name] = (key, value, 1)

    def clear(self) -> None:
        """Forget every measurement (the next frame measures): a new lens setting, a new camera."""
        with self._lock:
            self._kept.clear()


class _ShrunkMemo(StreamMemo):
    # a stream's memo as the decode of a frame shrunk by ``factor`` sees it (a frame of ``shape``,
    # or its window from column ``x0``, ``ratio`` full px per shrunk px along the rows): the
    # aberration fit is kept in the full frame's px (delta = a + k x), whatever the window, and
    # read in the shrunk frame's: x = c + ratio xs with c = x0 + (ratio - 1) / 2 (pixel centres),
    # delta = ratio delta_s, so a_s = (a + k c) / ratio and the same k

    def __init__(self, memo: StreamMemo, shape, factor: float, x0: int, ratio: float):
        self.memo, self.shape, self.factor = memo, tuple(shape), float(factor)
        self.ratio, self.c = float(ratio), float(x0) + 0.5 * (float(ratio) - 1.0)
        self.every = memo.every

    def _key(self, key):
        return ((self.shape, self.factor),) + tuple(key[1:])

    def get(self, name, key):
        kept, age = self.memo.get(name, self._key(key))
        if kept is not None and name == "lateral_ca" and kept[1] is not None:
            a, k = kept[1]
            kept = (kept[0], ((a + k * self.c) / self.ratio, k))
        return kept, age

    def put(self, name, key, value) -> None:
        if name == "lateral_ca" and value[1] is not None:
            a, k = value[1]
            value = (value[0], (self.ratio * a - k * self.c, k))
        self.memo.put(name, self._key(key), value)

    def clear(self) -> None:
        self.memo.clear()


def _reused(age: int) -> str:
    # stats['stream']'s word for a measurement an earlier frame made
    return f"reused (measured {age} frame{'' if age == 1 else 's'} before)"


def _choose_resample_memo(img: np.ndarray, params: DecodeParams, memo: StreamMemo | None, note: dict) -> tuple:
    # choose_resample, through the stream memo when there is one (kept only when measured)
    if memo is None or params.resample != 0:
        return choose_resample(img, params)
    key = (img.shape[:2], float(params.camera_gamma), float(params.dark_level))
    kept, age = memo.get("resample", key)
    if kept is not None:
        note["resample"] = _reused(age)
        return kept
    shrink = choose_resample(img, params)
    if math.isfinite(shrink[1]):
        memo.put("resample", key, shrink)
    note["resample"] = "measured"
    return shrink


def decode(image_rgb, pattern: PatternSpec, params: DecodeParams = DecodeParams(), *,
           keep_stages: bool = False, stripe_range: np.ndarray | None = None,
           memo: StreamMemo | None = None) -> StripeMap:
    """Decode one camera frame of the green-blue stripe pattern.

    image_rgb : (H, W, 3) uint8 RGB (uint16 and float in [0, 1] are converted).
    pattern : the projected pattern (stripe width, markers).
    params : :class:`DecodeParams`.
    keep_stages : also return the intermediate images in ``StripeMap.stages`` (previews).
    stripe_range : optional (2, H, W) float32, the absolute stripe indices (low, high; NaN: no
        bound) each pixel can see inside the scanner's working volume -- a calibration and a depth
        range give it (:meth:`gbscan.scan.Scanner.stripe_range`).  A prior for the indexing: it
        never chooses a region's offset, it rules out runner-up offsets that would put the whole
        region outside the volume, so regions whose few markers fit two far-apart offsets are
        indexed; a region whose best offset lies outside is dropped ("outside the working volume").
    memo : a :class:`StreamMemo` shared by the frames of one stream: the resampling factor and
        the lateral chromatic aberration measured on one frame are reused on the next ones
        (re-measured every ``memo.every`` frames; ``stats['stream']`` says which).  None: every
        frame measures them.

    Stages 1-3 run fused (``kernels.balance_samples``: the colour balance's samples, then
    ``kernels.stream_frame``: linearise, blur and classify in one pass over the rows) when
    :func:`fast_path` allows (vertical stripes, no blur across them, global colour balance, no
    stages kept); otherwise the named functions run one after another.  Both give bit-identical
    results (same row arithmetic).  ``stats['ms']``: input (validation; + linearisation on the
    staged path), blur (on the fast path: only the balance samples), balance, classify (on the
    fast path: linearisation, blur and classification), unwrap, index, subpixel, finish, total.

    A frame whose stripes are wide in the camera (``DecodeParams.resample``: automatically over
    ``RESAMPLE_ABOVE_PX`` camera px per stripe, e.g. a camera with more pixels than the paper's) is
    decoded shrunk in linear light to about ``RESAMPLE_TO_PX`` px per stripe, and the result is
    expanded back to every pixel of the frame (``kernels.upsample_stripes``); ``stats`` then
    carries ``resample`` (the factor), ``decoded_size`` and ``ms`` ``resample`` / ``upsample``.
    ``stats['stripe_camera_px']``: the frame's camera px per stripe read from its colour runs.

    The frame's colour resolution is checked first (``DecodeParams.subsampled_chroma``: a
    chroma-subsampled frame's absolute index is withheld, ``stats['chroma']``) and the lens's
    lateral chromatic aberration measured on its boundaries (``DecodeParams.lateral_ca``,
    ``stats['lateral_ca']``).

    Returns a :class:`StripeMap`.  Raises GBError for unusable input (grey image, bad dtype,
    NaN); an image without a usable stripe signal gives an empty StripeMap whose ``stats['why']``
    says why.
    """
    if not isinstance(pattern, PatternSpec):
        raise GBError(f"decode: pattern must be a gbscan.pattern.PatternSpec, got {type(pattern).__name__}")
    if not isinstance(params, DecodeParams):
        raise GBError(f"decode: params must be a DecodeParams, got {type(params).__name__}")
    if memo is not None and not isinstance(memo, StreamMemo):
        raise GBError(f"decode: memo must be a gbscan.decode.StreamMemo or None, got {type(memo).__name__}")
    t0 = time.perf_counter()
    img = validate_image(image_rgb)
    note: dict = {}
    shrink = _choose_resample_memo(img, params, memo, note)
    # a frame decoded shrunk by 2 or more averages each pixel pair's shared colour into one decoded
    # pixel: its stripes keep their colours, and it is not checked (see SUBSAMPLED_CHROMA_SHRINK)
    if params.subsampled_chroma == "off" or shrink[0] >= SUBSAMPLED_CHROMA_SHRINK:
        return _stream_note(_decode(img, pattern, params, keep_stages, stripe_range, t0, shrink, memo), memo, note)
    from .chroma import chroma_check

    t1 = time.perf_counter()
    chk = chroma_check(img)
    t2 = time.perf_counter()
    sm = _stream_note(_decode(img, pattern, params, keep_stages, stripe_range, t0 + (t2 - t1), shrink, memo),
                      memo, note)
    ms = sm.stats.setdefault("ms", {})
    ms["chroma"] = round((t2 - t1) * 1e3, 3)
    if "total" in ms:
        ms["total"] = round(ms["total"] + ms["chroma"], 3)
    withheld = chk.subsampled and params.subsampled_chroma == "withhold"
    sm.stats["chroma"] = {"score": None if not math.isfinite(chk.score) else round(chk.score, 3),
                          "score_cosited": None if not math.isfinite(chk.score_cosited) else round(chk.score_cosited, 3),
                          "subsampled": chk.subsampled, "withheld": withheld}
    if withheld:
        withhold(sm, f"absolute stripe index withheld: {chk.describe()}; the stripes' colours smear and whole "
                     "regions land on wrong stripes. Capture RGB or raw frames (a camera format without chroma "
                     "subsampling, lossless files), or decode it anyway, wrong stripes possible: "
                     "DecodeParams.subsampled_chroma='decode' (command line: --decode-param subsampled_chroma=decode)")
    return sm


def _stream_note(sm: StripeMap, memo: StreamMemo | None, note: dict) -> StripeMap:
    # stats['stream'] of a decode with a memo: what it measured and what it reused
    if memo is not None:
        sm.stats["stream"] = {**sm.stats.get("stream", {}), **note}
    return sm


def withhold(sm: StripeMap, why: str) -> StripeMap:
    """Report nothing of a decoded frame, in place: every reported pixel becomes ``unindexed``
    (column NaN, stripe -1, confidence 0, ``column_sigma`` NaN), the relative unwrapping is kept,
    the counts follow and ``stats['why']`` says why.  Returns ``sm``."""
    ok = sm.mask == OK
    sm.mask[ok] = UNINDEXED
    sm.column[ok] = np.nan
    sm.stripe[ok] = -1
    sm.confidence[ok] = 0
    if sm.column_sigma is not None:
        sm.column_sigma = np.full(sm.mask.shape, np.nan, np.float32)
    sm.stats.update(_count_reasons(sm.mask))
    sm.stats["why"] = why
    return sm


def _decode(img: np.ndarray, pattern: PatternSpec, params: DecodeParams, keep_stages: bool,
            stripe_range: np.ndarray | None, t0: float, shrink: tuple | None = None,
            memo: StreamMemo | None = None) -> StripeMap:
    # decode() of a validated frame (its chroma checked or not); t0: the clock at its start (the
    # chroma check's time left out); shrink: choose_resample's answer for it, when known; memo:
    # the stream's (the aberration fit read from it and kept in it)
    from . import kernels
    from . import unwrap as uw

    ms: dict[str, float] = {}
    H, W = img.shape[:2]
    if stripe_range is not None:
        stripe_range = np.asarray(stripe_range)
        if stripe_range.shape != (2, H, W) or stripe_range.dtype != np.float32:
            raise GBError(f"decode: stripe_range must be a (2, {H}, {W}) float32 array (low, high stripe per "
                          f"pixel), got {stripe_range.dtype} {stripe_range.shape}")
    factor, frame_px = choose_resample(img, params) if shrink is None else shrink
    if factor > 1.0:   # wide stripes in the camera: decode the frame shrunk to the validated width
        return _decode_resampled(img, factor, frame_px, pattern, params, keep_stages, stripe_range, memo)
    snr = None
    if params.blur_sigma_along_px is None:  # automatic: from this frame's stripe SNR
        sigma, snr = auto_blur_sigma(img, params)
        params = _with_sigma(params, float(sigma))
    dark_why = ("image is dark: no projected light seen "
                f"(green/blue never reach dark_level={params.dark_level:g} linear DN)")
    frame, shape, window = img, (H, W), None   # the whole frame; the decoded window (crop)
    if fast_path(params, keep_stages):
        # stages 1-3 fused: the colour balance's samples blurred alone, then one pass over the rows
        # (linearise, blur, classify; rows in rings, a per-thread workspace reused from frame to
        # frame like the other scratch).  ms: "blur" the samples, "classify" the row pass.
        ws = _workspace(H, W)
        lut = _lut(float(params.camera_gamma))
        kh = _gauss_half(params.blur_sigma_along_px)
        thr_w = _threshold_window(params)
        t = time.perf_counter()
        ms["input"] = (t - t0) * 1e3
        kernels.balance_samples(img, lut, kh, *ws.samples)
        t1 = time.perf_counter()
        ms["blur"] = (t1 - t) * 1e3
        sg, sb = _sample_scales(*ws.samples)
        t2 = time.perf_counter()
        ms["balance"] = (t2 - t1) * 1e3
        norm_w = int(params.norm_window_px) | 1
        if params.crop:
            # the rest runs on the lit window alone (the same result: outside it every pixel is
            # dark); the colour balance and the blur's SNR above are the whole frame's
            window = lit_window(img, params, kh.size - 1, thr_w, norm_w)
        if window is not None:
            img, stripe_range = _cut(window, img, stripe_range)
            H, W = img.shape[:2]
        gn, bn, contrast, reason = ws.views(H, W)
        labels = np.empty((H, W), np.uint8)
        top = kernels.stream_frame(img, lut, kh, sg, sb, thr_w, norm_w, *_stage3_args(params),
                                   *ws.rings(*kernels.stream_rows(kh.size - 1, thr_w), width=W),
                                   labels, reason, gn, bn, contrast)
        if top == 0 or lut[top] < params.dark_level:
            ms["classify"] = (time.perf_counter() - t2) * 1e3
            return empty_stripemap(shape, pattern, DARK, dark_why, {"ms": ms})
        cls = Classified(labels, reason, None, None, gn, bn, contrast)
        blurred = balanced = None
    else:
        g_lin, b_lin, raw_max = linearize(img, params.camera_gamma)
        t = time.perf_counter()
        ms["input"] = (t - t0) * 1e3
        if int(raw_max.max()) == 0 or float(cv2_max(g_lin, b_lin)) < params.dark_level:
            return empty_stripemap((H, W), pattern, DARK, dark_why, {"ms": ms})
        blurred = [motion_blur(x, params.blur_sigma_along_px, params.blur_sigma_across_px, params.stripe_angle_deg)
                   for x in (g_lin, b_lin)]
        t1 = time.perf_counter()
        ms["blur"] = (t1 - t) * 1e3
        balanced = colour_balance(blurred, params.balance_window_px)
        t2 = time.perf_counter()
        ms["balance"] = (t2 - t1) * 1e3
        cls = classify(blurred, balanced, (g_lin, b_lin), raw_max, params)
    t3 = time.perf_counter()
    ms["classify"] = (t3 - t2) * 1e3
    if not cls.labels.any():
        reason = cls.reason if window is None else _paste(window, shape, _DARK_FILL["mask"], cls.reason)
        why = ("image is saturated" if (reason == SATURATED).mean() > 0.5 else
               "no stripes found: no pixel shows green/blue modulation (uniform colour, out of focus, or no pattern)")
        sm = empty_stripemap(shape, pattern, LOW_CONTRAST, why, {"ms": ms})
        sm.mask[:] = reason
        sm.mask[sm.mask == OK] = LOW_CONTRAST
        sm.stats.update(_count_reasons(sm.mask))
        return sm

    located = {}
    ox = 0 if window is None else window[2]   # positions along the rows are the frame's (same rounding)

    def locate(sg):
        # the boundary positions of step 1's segments; a retry unwraps the same labels, so the
        # same segments (kept for it) and positions.  Lateral chromatic aberration is measured on
        # the first segments located and taken out of every set, before the unwrapping's spacing
        # and tilt cuts read them
        if located.get("segs") is not sg:
            x = subpixel_boundaries(cls, sg, ox)
            if params.lateral_ca:
                if "ca" not in located:
                    # (a stream's memo: the fit of an earlier frame of the same size and rule)
                    ca_key = (shape, float(params.lateral_ca_t), float(params.lateral_ca_min_px))
                    kept, age = memo.get("lateral_ca", ca_key) if memo is not None else (None, 0)
                    if kept is not None:
                        located["ca"], located["ca_fit"] = kept
                        located["stream"] = _reused(age)
                        if located["ca_fit"] is not None:
                            x = correct_lateral_ca(sg, x, *located["ca_fit"])
                    else:
                        x, located["ca"], located["ca_fit"] = lateral_chromatic_aberration(cls, sg, x, shape[1],
                                                                                          params, ox)
                        if memo is not None:
                            located["stream"] = "measured"
                            if located["ca"] is not None:
                                memo.put("lateral_ca", ca_key, (located["ca"], located["ca_fit"]))
                elif located["ca_fit"] is not None:
                    x = correct_lateral_ca(sg, x, *located["ca_fit"])
            located["segs"], located["x"] = sg, x
        return located["x"]

    un = uw.unwrap(cls.labels, params.unwrap, locate=locate)
    t4 = time.perf_counter()
    ms["unwrap"] = (t4 - t3) * 1e3
    n_reg = int(un.region_px.size)
    idx = uw.index_regions(cls.labels, un.relative, un.region, n_reg, pattern, params.unwrap, stripe_range)
    segments1 = located.get("segs")
    retry = _retry_welds(cls, un, idx, pattern, params, stripe_range, locate, segments1)
    retry_px, retry_gain, split_gain = None, 0, 0
    if retry is not None:
        un, idx, retry_gain, retry_px = retry
    split = _split_welds(cls, un, idx, pattern, params, stripe_range, locate, segments1, retry_px)
    if split is not None:
        un, idx, split_gain = split
    n_reg = int(un.region_px.size)
    # a region whose markers do not fit because a strip of another surface is welded in beside
    # it: indexed without the stretches that contradict it (which the pass below then reports)
    idx, peeled = uw.peel_conflicts(cls.labels, un, idx, pattern, params.unwrap, cls.gn, cls.bn, stripe_range)
    # the regions the repairs above left ambiguous whose runner-ups contradict enough more stripes
    # (after them: indexing such regions first changed what the repairs did, and a retry no
    # longer taken let a panel link 8 stripes off)
    idx = uw.index_by_stripes(idx, params.unwrap)
    # stretches of rows whose own markers contradict their region's offset (a surface welded in
    # across a depth edge): reported as unindexed.  finish_pixels keeps any non-zero input reason.
    _mark_spans(cls.reason, uw.marker_conflicts(cls.labels, un, idx, pattern, params.unwrap, cls.gn, cls.bn),
                UNINDEXED)
    t5 = time.perf_counter()
    ms["index"] = (t5 - t4) * 1e3

    segs = un.segments
    jx = segs.j_x if segs.j_x is not None else locate(segs)
    ca = located.get("ca")
    seg_reg = un.seg_region
    # relative columns for every region (consistent inside it; unknown multiple of 2*stripe_px)
    j_bnd = kernels.junction_index(segs.j_rel, segs.j_seg, un.seg_P)
    jx64, locking, n_locking = correct_locking(jx.astype(np.float64), segs, params.boundary_fit_half,
                                               params.locking_bins, params.locking_min_count)
    jx64, fit_alt, _ = choose_fit(jx64, segs, seg_reg, params.boundary_fit_half, params.boundary_fit_alt_half)

    # each segment's absolute shift (projector px) from its region's offset, where the indexing
    # (before the linking: every call below sees the same) gave one; NaN elsewhere
    contact_shift = np.zeros(0)
    if params.contact_regions and n_reg:
        reg_sh = np.where(idx.indexed, idx.offset * float(pattern.stripe_px), np.nan)
        contact_shift = np.where(seg_reg >= 0, reg_sh[np.maximum(seg_reg, 0)], np.nan).astype(np.float64)

    def columns(seg_ok, column_all=None):
        # interpolate_columns for the segments seg_ok; from column_all (every segment's) by a copy
        # when it is at hand (same values: each pixel belongs to one segment span)
        ok = seg_ok.astype(np.uint8)
        if column_all is not None and _REUSE_LINK_WORK:
            col, exact = kernels.select_columns(column_all, segs.row, segs.u0, segs.u1, ok)
            if exact:
                return col
        # (a segment's columns do not depend on which others are accepted: the contact rule
        # looks at its neighbours whatever their fate, so the copy above is exact)
        return kernels.interpolate_columns(H, W, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, ok, jx64, j_bnd,
                                           float(pattern.stripe_px), float(params.extrapolate),
                                           float(params.contact_ratio), int(params.extrapolate_fit),
                                           int(params.contact_gap_px), ox, contact_shift)

    rim_done = None
    late_spans = None
    linked = None   # (n_reg,) bool, the regions the linking indexed (None: it indexed none)
    if params.unwrap.link_votes > 0 and pattern.markers and idx.indexed.any() and \
            (un.isolated.any() or not idx.indexed.all()):
        # every component's columns: the small / unindexed ones may be indexed through neighbours
        column_all = columns(np.ones(segs.n, np.uint8))
        column_rel = columns(seg_reg >= 0, column_all)
        memo: dict = {}
        n_new = _link_through_neighbours(cls, un, idx, column_all, column_rel, pattern, params, memo)
        if n_new != n_reg or un.stats.get("link_components_linked", 0):
            n_reg = n_new
            # the linked regions' own rows against their markers, as the marker-indexed ones
            # above (a linked region may carry a strip of another surface welded in)
            linked = np.array([w == "linked" for w in idx.why], bool)
            late_spans = uw.marker_conflicts(cls.labels, un, dataclasses.replace(idx, indexed=idx.indexed & linked),
                                             pattern, params.unwrap, cls.gn, cls.bn)
            column_rel = columns(un.seg_region >= 0, column_all)
            if _REUSE_LINK_WORK and "reason" in memo:
                # the votes' rim rule, again only on the rows whose window saw a linked segment
                reg_off = np.where(idx.indexed, idx.offset * pattern.stripe_px, np.nan).astype(np.float32)
                rim_done = _rim_rule_rows(column_rel, un.region, reg_off, cls.reason, memo["reason"],
                                          memo["changed_rows"], params, labels=cls.labels)
        elif _REUSE_LINK_WORK:
            # nothing linked: the rim rule the votes ran on a copy is the final one (same inputs)
            rim_done = memo.get("reason")
    else:
        column_rel = columns(seg_reg >= 0)
    if rim_done is not None:
        np.copyto(cls.reason, rim_done)
    elif params.rim_bias_px > 0 or params.rim_end_px > 0:
        reg_off = np.where(idx.indexed, idx.offset * pattern.stripe_px, np.nan).astype(np.float32)
        rim_rule(column_rel, un.region, reg_off, cls.reason, params, labels=cls.labels)
    if late_spans is not None:
        _mark_spans(cls.reason, late_spans, UNINDEXED)
    joined = _NO_SOURCES
    if params.join_transitions and n_reg:
        # one-pixel stripe transitions inside an indexed region that the classifier called dark
        # (both channels under min_level) report their signal: ordinary pixels for finish_pixels
        # and the guards.  After the rim rules: both neighbours passed them (the pixel's own
        # column lies between theirs), and a pixel the rules read as signal-less keeps masking
        # its stretch's end next to a silhouette (joined before them: sweep on depth edges +25)
        joined = kernels.join_transitions(cls.reason, cls.labels, un.region, cls.gn, cls.bn, cls.contrast,
                                          np.ascontiguousarray(idx.indexed, dtype=np.bool_),
                                          float(params.min_level), float(params.min_contrast), DARK, OK)
    t6 = time.perf_counter()
    ms["subpixel"] = (t6 - t5) * 1e3

    # -- masks, stripe, confidence
    nr = max(n_reg, 1)
    reg_indexed = np.zeros(nr, bool)
    reg_margin = np.ones(nr, np.float32)
    reg_shift = np.zeros(nr, np.int64)
    if n_reg:
        reg_indexed[:] = idx.indexed
        reg_shift[:] = idx.offset
        if pattern.markers:
            reg_margin[:] = np.clip((idx.runner_up - idx.mismatch) / np.maximum(idx.evidence, 1), 0, 1)
    region = un.region.copy() if keep_stages else un.region  # finish joins one-pixel gaps in place
    mask, column, stripe, conf, counts = kernels.finish_pixels(
        cls.reason, cls.labels, region, un.relative, column_rel, un.inconsistent, reg_shift, reg_indexed,
        reg_margin, cls.contrast, int(pattern.stripe_px), int(pattern.n_stripes), float(params.min_contrast),
        len(REASONS), CONF_FLOOR)
    n_guard = rim_guard(mask, column, stripe, conf, guard_rows(params), counts, guard_end_rows(params),
                        bool(params.rim_guard_no_boundary), img, float(params.rim_end_dim_ratio),
                        float(params.camera_gamma), guard_lit_rows(params))
    n_step = step_guard(img, mask, column, stripe, conf, region, params, counts)
    n_sandwich = sandwich_guard(mask, column, stripe, conf, region, pattern, params, counts)
    jump = {}
    n_piece, n_alone = piece_check(mask, column, stripe, conf, cls.labels, region, pattern, params, counts, n_reg,
                                   linked, jump, (column_rel, reg_shift, reg_indexed))
    _unreported(counts, int(kernels.drop_orphans(mask, column, stripe, conf, OK, ISOLATED)), ISOLATED)
    sigma = None
    floor = None
    if params.confidence_spread_px > 0:
        # (a fixed blur: the frame's noise for the model's floor all the same, ~0.1 ms)
        floor = spread_floor_px(snr if snr is not None else frame_snr(frame, params),
                                float(params.blur_sigma_along_px))
        sigma = column_spread(mask, column, conf, params, floor_px=floor, sources=joined)
    rest = None
    if window is not None:
        # back to the frame's pixels; the maps a scan does not read when first read
        column, stripe, conf, mask = _paste_scan_maps(window, shape, column, stripe, conf, mask, counts)
        if sigma is not None:
            sigma = _paste(window, shape, _DARK_FILL["column_sigma"], sigma)
        rest = _Deferred((window, shape, un.relative, region, cls.labels, column_rel), "_paste_maps")
    t7 = time.perf_counter()
    ms["finish"] = (t7 - t6) * 1e3
    ms["total"] = (t7 - t0) * 1e3

    stats = _reason_stats(counts)
    stats.update(un.stats)
    stats["regions_indexed"] = int(idx.indexed.sum())
    stats["regions_unindexed"] = int(n_reg - idx.indexed.sum())
    stats["region_why"] = dict(sorted(collections.Counter(map(str, idx.why)).items())) if n_reg else {}
    stats["boundaries"] = int(np.isfinite(jx).sum())
    # the pixel locking taken out (camera px): junction types corrected, the largest correction
    stats["locking_types"] = n_locking
    stats["locking_max_px"] = round(float(np.abs(locking).max()), 4) if n_locking else 0.0
    # the boundary fit's windows (boundaries) and the regions that took the narrower one (choose_fit)
    stats["fit_boundaries"] = 2 * int(params.boundary_fit_half) + 1
    stats["fit_alt_boundaries"] = 2 * int(params.boundary_fit_alt_half) + 1
    stats["fit_alt_regions"] = int(np.count_nonzero(fit_alt))
    stats["weld_retry_px"], stats["weld_split_px"] = retry_gain, split_gain
    # regions indexed once the stretches their markers contradict were taken out (peel_conflicts)
    stats["regions_peeled"], stats["peeled_px"] = int(np.count_nonzero(peeled)), int(peeled.sum())
    # of the "rim" pixels: masked by the guard rows (rim_guard) and by the brightness-step guard
    stats["rim_guard_px"], stats["rim_step_px"] = int(n_guard), int(n_step)
    stats["sandwich_px"] = int(n_sandwich)
    # pieces cut off from their region's body: by their own markers, for nothing continuing them
    stats["piece_px"], stats["piece_alone_px"] = int(n_piece), int(n_alone)
    # pieces cut off along lines where the column jumps (and those lines' pixels beside them)
    stats["jump_piece_px"] = jump.get("jump_piece_px", 0)
    stats["jump_line_px"] = jump.get("jump_line_px", 0)
    stats["transitions_joined"] = int(joined.size)
    if ca is not None:
        stats["lateral_ca"] = dict(ca)
    if "stream" in located:
        stats["stream"] = {"lateral_ca": located["stream"]}
    stats["decoded_window"] = _window_stat(window, shape)
    stats["ms"] = {k: round(v, 3) for k, v in ms.items()}
    stats["blur_sigma_along_px"] = float(params.blur_sigma_along_px)
    if math.isfinite(frame_px):
        stats["stripe_camera_px"] = round(float(frame_px), 2)
    if snr is not None:
        stats["snr"] = round(float(snr), 2)
    if floor is not None:
        stats["spread_floor_px"] = round(float(floor), 4)
    if not pattern.markers:
        stats["why"] = "pure pattern (no markers): relative stripe index only, see StripeMap.relative/region"
    stages = None
    if keep_stages:
        stages = {"blurred": np.dstack(blurred), "balanced": np.dstack(balanced), "d": cls.d, "threshold": cls.thr,
                  "labels": cls.labels, "gn": cls.gn, "bn": cls.bn, "contrast": cls.contrast, "relative": un.relative, "region": un.region,
                  "believable": np.where(segs.seg >= 0, un.believable[np.maximum(segs.seg, 0)], False),
                  "index": idx}
    # (column_rel is NaN outside regions: finish_pixels did it in place)
    if rest is not None:
        return StripeMap(column, stripe, conf, mask, rest, rest, rest, stats, pattern, stages, rest, sigma)
    return StripeMap(column, stripe, conf, mask, un.relative, region, cls.labels, stats, pattern, stages,
                     column_rel, sigma)
