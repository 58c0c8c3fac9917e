"""Unwrapping the green-blue stripes (the paper's seven steps) and absolute indexing by markers.

Input: a colour-class image ``labels`` (H, W) uint8 (``gbscan.pattern.NONE/GREEN/BLUE/CYAN``)
from :mod:`gbscan.decode`.  Output: for every pixel a *relative* stripe index that is consistent
inside a connected *region*, then (with cyan markers) the region's absolute offset.

Vocabulary (the paper gives only the step names; this is how each is realised):

* **run** -- a maximal horizontal stretch of one colour in a row.
* **segment** -- a maximal chain of runs along a row joined by valid stripe transitions; inside a
  segment the relative index ``rel`` counts transitions, its parity fixed by colour (green even,
  blue odd; cyan markers take the count).  A row usually holds several segments (shadows,
  occlusions, objects).  Segments, not rows, are the units related to the row above.
* **edge** -- a vote between a segment and an overlapping segment of the row above: every pixel
  whose upper neighbour has the same colour votes for ``rel_above - rel``; the winning (even)
  offset, its votes ``n_agree`` and the agreement fraction ``n_agree / n_same`` make the edge.
  *Strong* edges have ``n_agree >= n_ref_pixels`` and fraction ``>= agree_frac``.
* **region** -- segments joined by strong edges whose offsets are mutually consistent
  (union-find with potentials, strongest edges first; a contradicting edge is a *conflict*, not
  applied).  All indices inside a region share one unknown even offset.

The seven steps (paper wording -> function):

1. *unroll each row by transitions along it* -> :func:`unroll_rows` (runs -> segments; spike
   runs and small gaps cleaned, parity contradictions end a segment), then
   :func:`cut_depth_edges` (a transition where the sub-pixel boundary spacing jumps is a depth
   edge, not a stripe boundary of one surface: the segment is cut there) and
   :func:`cut_unlocated` (the same check across boundaries the sub-pixel locator cannot find).
2. *unroll every row by relation with the upper neighbour row* -> :func:`relate_rows` (edges;
   an edge is strong with enough agreeing votes, few dissenters, enough overlap and colours kept).
3. *determine believable rows* -> :func:`believable_segments`: a segment is believable when its
   stripes continue, through strong edges, over at least ``n_ref_rows`` rows.
4. *unroll each pixel by relation with its upper neighbour in believable rows* ->
   :func:`link_believable`: believable segments are joined (strongest edges first) into regions;
   every pixel of them gets ``rel + P[segment]``.
5. *unroll each row by transitions again* -> :func:`split_doubtful`: a segment that is not
   believable is cut where its relation to the rows above and below changes (an inserted or lost
   stripe shifts the index of the rest of the row by two): each piece is a new segment.
6. *unroll every row by relation with the upper neighbour* -> :func:`attach_doubtful`: the pieces
   are related to their neighbours again and each joins at most one region through a strong edge
   (a doubtful piece never merges two regions).
7. *unroll each pixel by relation with its upper neighbour* -> :func:`check_pixels`: a pixel whose
   upper or lower neighbour has the same colour and region but another index is flagged.

No step optimises globally; each decision uses only a pixel's own row and its neighbour rows.
Absolute indexing (beyond the paper) is :func:`index_regions` (and :func:`index_by_stripes`, its
margin counted in stripes, which the decoder applies after its weld repairs);
:func:`marker_conflicts` then finds stretches of rows whose own markers contradict their
region's offset (a surface welded in across a horizontal depth edge where the stripes happen to
line up), which the decoder drops as unindexed.
Components the markers cannot index alone (too small, too few markers) are indexed through the
reported pixels around them by :func:`link_components` when the projector column continues into
them for exactly one offset (many agreeing votes, none elsewhere, markers consistent); the decoder
then checks the linked regions' rows with :func:`marker_conflicts` too.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from .errors import GBError
from .pattern import PatternSpec


@dataclass(frozen=True)
class UnwrapParams:
    """Parameters of the unwrapping and the absolute indexing.

    n_ref_pixels : votes (pixels) an edge between two segments needs to be strong.
    n_ref_rows : rows a segment's stripes must continue through to be believable (step 3).
    agree_frac : fraction of an edge's same-colour votes that must agree on its offset.
    min_overlap_frac : agreeing votes an edge needs, as a fraction of its shorter segment's length.
    same_frac : fraction of an edge's overlapping labelled pixels that must keep their colour.
    max_gap_px : unlabelled gap (px) a segment may bridge along a row.
    spacing_ratio : a row is cut where consecutive boundary spacings differ by more than this
        factor (a depth edge; 0 disables; needs sub-pixel boundaries, see :func:`unwrap`).
    bridge_ratio : the same test across boundaries the sub-pixel locator could not find
        (:func:`cut_unlocated`): a run of unlocated boundaries is kept only when the located ones
        on either side bridge it with a mean spacing within this factor of the spacing just left
        and just right of it; otherwise the row is cut at every one of them (0 disables).  Where a
        row crosses a silhouette with the stripes of both surfaces lined up (an even shift), the
        crossing is the one boundary the locator cannot find, so ``spacing_ratio`` never saw it,
        and the segment welded the two surfaces: at blur 1.75 px a sphere patch into the object
        below it (multi-object at 760 mm, 229 px 20 stripes off), at 2.5-3 px a strip of wall into
        a panel (moving frame 5, 114 px 28 stripes off).  0.3 % of the boundaries of
        ``scripts/sweep_decode.py`` are unlocated.  The sweep's wrong non-edge pixels at blur
        1.75 / 2.5 / 2.75 px: 237 / 144 / 62 -> 8 / 31 / 3; 1.1-1.25 fix the same pixels, 1.35
        misses the sphere patch (its bridge is 1.32 x the spacing beside it).  Coverage rises
        (the welds no longer split regions' markers): automatic blur 81.49 -> 81.80 % with
        ``link_hang_rows`` and ``link_slope_z_near`` (moving frame 0 +7.2 points, frame 9 and
        multi-object at 700 mm +1.3-1.5); noisy frames, with many unlocated boundaries, lose a
        little (hard presets -0.1 to -0.4 points).
    spike_px : runs of at most this many px flanked by one colour are noise (0: keep all).
    marker_flank_px : a run of at most this many px between a cyan marker and a longer run of the
        other colour, where the marker's flanks then disagree (``X Y C X``), is the mixed pixels of
        that flank and the marker classified as the other colour, and is absorbed into the flank
        (0: such a row is cut there).  Wide stripes cause it (the local threshold sees only the
        flank and the marker): on the sphere at 650 mm (seed 0) the limb facing the projector,
        10 camera px per stripe, was cut at every marker row.  Only beside a cyan run wider than
        ``2 * marker_flank_px`` (a marker seen wide; beside narrow ones such a run is often a real
        stripe whose twin across the marker was lost).  Measured: sphere and head seeds 0-2,
        reported +0.8-1.0 points (sphere seed 0: 91.4 -> 92.3 %); ``scripts/sweep_decode.py``
        81.38 -> 81.49 %, still 0 wrong pixels off depth edges, no scene loses coverage.
    marker_end_flank : (with ``marker_flank_px`` > 0) at the end of a row stretch (``. Y C X``,
        mirrored ``X C Y .``) a 1 px run ``Y`` between a marker (of any width) and the dark, whose
        colour contradicts the marker's other flank, is the mixed pixel of the marker and the dark
        and is unlabelled, so the marker stays with its surface instead of ending up a fragment
        ``Y C`` of its own (mask "isolated"), where a shadow or silhouette cuts through a marker
        stripe.  Measured
        (``scripts/sweep_decode.py``, 48 scenes): the real face 80.73 -> 81.38 % reported (frontal)
        and +0.04 to +0.5 on the other renders, the others 0 to +0.05; wrong pixels unchanged at
        every fixed blur 1 ... 3 px.  Scans (``scripts/coverage_study.py``): real face seeds 0-2
        80.0 / 79.0 / 79.0 -> 80.7 / 79.6 / 79.5 % kept (depth RMS 0.215 -> 0.217 mm), turned
        -30 / -15 / +15 / +30 degrees 0 / 0 / +0.3 / +0.1 points.  Dropping 2 px runs as well gained
        the frontal face more (+0.8) but lost the face turned +30 degrees 8.8 points (a real
        marker's flank dropped: the marker a stripe off its surface, the region ambiguous).
    min_region_px : regions smaller than this are dropped (mask "isolated").
    min_marker_px : pixels of a marker stripe a region must see for it to count as observed.
    min_markers : distinct markers a region must see to be indexed (three consecutive ones fix the
        offset by construction; two can, together with the marker-free stripes around them, when
        the margin test passes).
    index_margin : the best offset's mismatch must be lower than the runner-up's by this
        fraction of the region's marker evidence (or by ``index_margin_events`` marker events,
        when that is less).
    index_margin_events : the same margin counted in marker events: a marker event is one marker
        stripe seen where the offset expects none, or expected where the region shows green or
        blue, about ``evidence / (2 markers_seen)`` pixels.  The runner-up must mismatch by this
        many events more than the best (0: only ``index_margin``).  The fixed fraction asks for
        2 events of a region seeing 4 markers, 2.5 of one seeing 5, 4 of one seeing 8: so a region
        of 4 markers whose runner-up differs by exactly two events (a fake marker *and* a missed
        one) sat on the rule's edge, and big regions flipped in and out with the blur (moving frame
        8: a 9900-px panel, runner-up 682 px worse than the best, margin 691.5 px).  1.5 events
        rules out any single misread marker stripe.  Sweep (``scripts/sweep_decode.py``, 44 scenes):
        reported 83.20 -> 83.89 %, no index error added (the 7 wrong pixels it adds are a linked
        65-px fragment of a Bayer frame, half a stripe off under a horizontal crease).
    index_margin_stripes : a region left :data:`AMBIGUOUS` by the pixel margin above is indexed
        when every other candidate offset contradicts at least this many more *stripes* than the
        best (0: the pixel margin alone).  A stripe contradicts an offset when it shows
        ``min_marker_px`` cyan pixels where the offset puts a plain stripe, as many green/blue
        pixels where it puts a marker, or as many pixels outside the pattern
        (:func:`gbscan.kernels.score_offsets`, ``RegionIndex.stripe_margin``).  The pixel margin
        weighs each marker by its pixels: the multi-object scene's lower sphere sees four markers,
        the outer two short (its top and bottom); its runner-up contradicts exactly those and its
        short last stripe, 152 px against a margin of 233 px -- 3 % of the frame's lit pixels left
        unindexed.  In stripes the runner-up is 3 worse.  Over the seven sweep sets (239 frames,
        ``scripts/index_margin_study.py``), the scorings of regions left ambiguous whose pixels
        lie on one surface: a stripe margin of 1 would index 6 of 713 wrongly, 2 none of 452.
        2 is also the smallest margin no single misread stripe can turn into a wrong index: one
        misread moves the best's count and a runner-up's by one each, to a tie at worst.  The
        decoder applies it last (:func:`index_by_stripes`, after the weld repairs: retry, split,
        peel), so the repairs see what they saw before: applied inside the indexing it spared
        the retry of a frame whose re-unwrapping had kept a panel unlinked, and the panel linked
        8 stripes off (the multi-object scene at a 140-mm baseline), and it let a split cut a
        region whose part was then indexed 12 stripes off (175 mm).  ``scripts/sweep_decode.py``,
        no pixel on a wrong stripe added in any set: reported 83.76 -> 85.12 % (main), 91.83 ->
        92.66 (room light), 89.91 -> 90.72 (clean), 85.30 -> 87.07 (baselines), 88.74 -> 91.76
        (mirrored), 87.95 -> 89.13 (panels), 83.31 -> 84.12 % (layouts).  Their ``why`` is
        :data:`STRIPE_OK`.
    index_strong_stripe_px : a region left :data:`AMBIGUOUS` whose stripe margin is one short of
        ``index_margin_stripes`` is indexed too when that one stripe is seen well: for every
        candidate contradicting one stripe more than the best, a stripe it contradicts and the best
        does not shows at least this many contradicting pixels (``RegionIndex.stripe_strength``;
        0: never; why :data:`STRONG_OK`; the strength is measured for a margin of 1, so the rule
        acts with ``index_margin_stripes`` 2, the default).  A misread stripe is a few pixels; one that a welded
        strip of another surface brings in is as large as the strip's marker.  Over the thirteen
        sweep sets (431 frames, ``index_margin_stripes`` off so that every scoring is seen: 1 472
        scorings of ambiguous regions with a stripe margin of 1), the 11 at a wrong offset were
        regions holding another surface (3-37 % of their pixels), their telling stripe 12-48 px;
        at 60 px or more 182 scorings (347 000 px), none wrong.  Applied with the stripe margin,
        after the weld repairs.  ``scripts/sweep_decode.py`` (thirty-second session), no pixel on a
        wrong stripe added anywhere: the real face turned 20 degrees (seed 1) 72.83 -> 82.51 %
        reported, the 48 scenes 85.24 -> 85.36 %, mirrored 91.89 -> 92.33, baselines 87.81 ->
        88.17, held-out sets up to +0.59 points; on the two sets made before it was run
        (``holdout7``, ``faces``) 75.75 -> 75.87 % and unchanged, wrong pixels unchanged.
    max_mismatch : largest acceptable mismatch of the best offset, as a fraction of the evidence.
    conflict_run_px : a run of at least this many px whose marker/non-marker colour contradicts its
        region's offset is a disagreement (:func:`marker_conflicts`).
    conflict_events : disagreements a stretch of a row between agreeing markers must hold to be
        made unindexed.
    conflict_clean_level : a green/blue run on a marker stripe whose median ``min(gn, bn)`` (the
        classifier's locally normalised channels) is below this is a decisive disagreement alone
        (0 disables; needs the channels, see :func:`marker_conflicts`).  A marker lights both
        channels: the 202 markers missed (classified green/blue) on ``scripts/sweep_decode.py``'s
        35 scenes keep ``min(gn, bn)`` >= 0.204 (10 % below 0.32), while 180 of the 335 green/blue
        runs of other surfaces welded onto a marker stripe are below 0.15 (median 0.14).  On the
        sweep it takes the wrong non-edge pixels 609 -> 151 (a wall strip welded to the box, wall
        at 800 mm: 246 -> 12; the moving frames' panel strips welded to the wall, frames 4, 5, 7:
        12, 158, 71 -> 0, 0, 17) at coverage 82.03 -> 82.00 % (only those scenes lose pixels);
        0.15, 0.18 and 0.2 fix the same pixels.  Since the twenty-second session the run's
        *median* ``min(gn, bn)`` (numpy's: the mean of the middle two when even) rather than its
        mean: a lens with lateral chromatic aberration shifts the blue image against the green
        one, so a welded run's edge pixel mixes both channels (a 3-px run 0.05 / 0.07 / 0.37: mean
        0.16, median 0.07).  Through the simulator's lens at 1 px in the corners the sweep's 54
        wrong pixels off depth edges (a wall strip welded beside the box) go to 0, and 92 -> 0
        with the aberration applied to the finished frames; the lossless sweep loses 37 right
        pixels of one moving frame (a weld already masked, whose stretch now reaches them).
    conflict_confirm : an agreeing marker bounds a rejected stretch only when the next event
        beyond it agrees too (a strip of another surface puts one of its markers on a marker
        stripe of the region now and then); False: any agreeing marker bounds it, as before.  On
        the clean preset's multi-object scene 14 -> 0 wrong pixels off depth edges per seed; the
        48-scene sweep 83.76 -> 83.75 % reported, 150 -> 147 wrong on depth edges; JPEG q95
        4:4:4 63 -> 29 off them (docs/history.md, sixth session).
    conflict_persist_rows : a cyan run on a non-marker stripe between two runs of one colour (a
        marker's ``G C G`` or ``B C B``, not a fringe at a green|blue boundary nor a mixed pixel at
        a stretch's end) whose middle column stays cyan on the same stripe of the region for this
        many consecutive rows is a decisive disagreement alone: a marker of another surface, not a
        glint (0 disables).  At a horizontal contact a short strip of the surface above (3 stripes
        of a 7-row marker) links to the one below where their stripes line up, an even number
        apart, and holds one disagreement a row.  Sweep of 48 scenes through a lens with lateral
        chromatic aberration of 0.5 px: 2 -> 0 wrong pixels off depth edges (79 -> 66 on them);
        the same aberration applied to the finished frames at 0.4 px 7 -> 0, a luma sharpening of
        1.0 4 -> 0; the lossless sweep, room light, clean, baselines, JPEG 4:4:4 and the blur
        grid at 1 / 2 / 3 px unchanged bit for bit (docs/history.md, twenty-second session).
    conflict_extend : a rejected stretch does not stop at an agreeing marker (nor at its
        confirmation) that also agrees under the stretch's own shift -- the even shift under
        which the stretch's runs fit the pattern best, by at least ``conflict_events`` -- but runs
        on to the first run that fits the region and not that shift (see
        :func:`gbscan.kernels.marker_conflicts`).  The multi-object scene with its panel plain
        (``sim.scenes.multi_object(panel_albedo=...)``) at 700 mm: the wall's rows weld onto the
        panel's at its right silhouette 6 stripes off, where the marker gaps repeat (90, 96, 102),
        so the wall's first marker lands on the panel's 96 and the panel's 90 confirms it; 42-100
        wall pixels a frame before it stayed, 95 mm off in the scan, on 6 of the 45 frames of
        ``scripts/sweep_decode.py --set panels``.  Measured (twenty-seventh session; off / on):
        the panels set 88.08 -> 87.95 % reported, wrong pixels off depth edges 496 -> **0** (on
        them 367 -> 228); the 48 scenes 83.79 -> 83.76 %, room light 91.85 -> 91.83 %, clean
        89.93 -> 89.91 %, mirrored 88.83 -> 88.74 %, baselines 85.37 -> 85.30 %, none wrong
        before or after; scans (``scripts/coverage_study.py``, seeds 0-2) of the sphere, head and
        real face unchanged, multi-object 0-0.1 points fewer.  Without the ``conflict_events``
        floor on the shift (one agreement enough, ties by the dozen) every set lost 0.1-0.2
        points and the multi-object scans 0.3-0.5.  The peel (:func:`peel_conflicts`) takes its
        stretches without it (nor ``conflict_grow``): the runs it adds are no evidence either
        way, and taking them out too left a panel too small to index (4 400 pixels dropped).
    conflict_grow : the rejection of a row stretch passes to the rows above and below whose
        segments in the same region hold no agreeing run of their own, row after row
        (:func:`gbscan.kernels.grow_conflicts`): a welded strip 3-4 stripes wide has a marker in
        some rows only, and its rows without one were reported with the region's offset.  The
        multi-object scene at 800 mm with its wall at 1 231 mm (``scripts/sweep_decode.py --set
        layouts``): a strip of the wall under the box, welded to it where their stripes line up
        20 stripes apart, 80 / 73 wrong pixels (seeds 0, 1) -> 0 / 3.  Measured (twenty-seventh
        session; off / on): the layouts set 302 -> 134 wrong pixels off depth edges, 83.31 %
        reported either way; the 48 scenes, the mirrored, panels, room-light, clean and
        baselines sets unchanged to 0.01 points.
    link_votes : a component that cannot be indexed alone (too small, too few markers) is indexed
        through the reported pixels around it when at least this many column-continuity votes
        agree on its offset (:func:`link_components`; 0 disables).
    link_lines : the agreeing votes must come from at least this many distinct rows/columns.
    link_tol_px : a vote agrees when its residual is within this many projector px of an offset
        (a quarter of the 16 px period of an even stripe shift by default).
    link_agree_frac : fraction of all of the component's votes that must agree on one offset.
    link_gap_px : unreported pixels a horizontal vote may reach across.
    link_marker_frac : largest fraction of the component's pixels whose colour may contradict
        the markers at the linked offset (cyan on a non-marker stripe, green/blue on a marker).
    min_believable_junctions : a segment with fewer stripe boundaries than this holds no complete
        stripe and is never believable (step 3): its relation to the rows around rests on one
        boundary, and a chain of such bits can bridge two surfaces at a horizontal depth edge where
        their stripes line up.  Doubtful, each still joins at most one region (step 6).  Measured
        with ``scripts/sweep_decode.py`` (35 scenes): 0 -> 2 takes the wrong non-edge pixels from
        6199 to 1972 at the same coverage (82.09 -> 82.06 %); the multi-object scene at 600 mm
        (seed 1) from 2309 to 3.
    link_rows, link_reach_rows : a component taller than ``link_reach_rows`` rows is linked only
        when its agreeing votes come from candidate pixels in at least ``link_rows`` distinct rows
        (1: no such test).  A tall component touching the reported pixels along one row only may
        hang below a horizontal depth edge where two surfaces' stripes line up, or below a strip
        of another surface welded into the voting region: the columns continue exactly there and
        its few markers may fit both offsets.  Off by default: on the sweep ``link_rows=3`` takes
        the wrong non-edge pixels 1972 -> 524 but the coverage 82.06 -> 79.82 % (correct tall
        components linked through one row are dropped too: sphere seed 1 94.9 -> 86.3 %).
    link_slope_tol, link_slope_z, link_slope_rows, link_slope_half_px, link_slope_below_rows :
        the slope test of :func:`link_components` for a tall component (over ``link_reach_rows``
        rows) whose agreeing votes come from fewer than ``link_slope_below_rows`` rows (0: every
        component): it hangs at a horizontal contact, where the columns of two surfaces can line
        up for an even stripe shift (a panel in front of a wall), but the column's slope along the
        row (camera px per stripe) changes with the distance (3.8 -> 3.4 px per stripe, panel at
        ~680 mm, wall behind).  Slopes ``link_slope_rows`` rows into the component and into the
        voting region (past the rows the along-stripe blur mixes; over +-``link_slope_half_px`` px)
        must not differ by more than ``link_slope_tol`` with a z-score over ``link_slope_z``;
        ``3 * link_slope_rows`` rows into the voting region, per side, not by twice that (see
        :func:`_slope_jumps`; ``link_slope_tol=0`` disables).  On ``scripts/sweep_decode.py``
        (35 scenes) it takes the wrong non-edge pixels 1972 -> 609 (moving multi-object frames 5
        and 6: 768 -> 158, 780 -> 27), coverage 82.06 -> 82.03 % (step_hard 84.40 -> 84.36 %, no
        other scene changes; the test scenes are unchanged).
    link_slope_z_near : the z-score the *near* test needs (the deep one keeps ``link_slope_z``):
        the near slopes are those of the surface right at the contact, the deep ones may sit on
        another surface past a welded strip.  With the boundary fit (``DecodeParams.
        boundary_fit_half`` = 3) moving frame 5 at blur 3 px had a panel (799 px, one marker)
        linked 8 stripes off through one row, its slope 11 % below the wall's (3 x the
        tolerance) at z = 12.3 (the fitted boundaries spread the votes): 15 -> 10 takes the
        sweep's wrong non-edge pixels at 3 px 353 -> 1; one z of 10 for both tests would also
        refuse a correct 1500-px component of that frame at 2 px (its deep ratio 0.11).
    link_hang_rows : a component of more than this many rows (and at most ``link_reach_rows``)
        whose agreeing votes all come from one row passes the slope test too, the rule of
        ``link_slope_unmeasured`` included (0: only tall components do).  It hangs from one
        contact row, the shape of a weld where two surfaces' stripes line up: at the foot of the
        moving frames' panels, marker-free fragments of 6-7 rows (20-80 px) welded to the
        surface below by one lined-up row were linked 6-8 stripes off through it (frames 1 and 7,
        blur 1.75-3 px).  Components held by votes from two sides are left alone: lowering
        ``link_reach_rows`` to 5 instead fixes the same pixels but refuses sandwiched 6-row
        strips of the face (head at 650 mm, seed 0: 85.0 -> 83.2 % kept).
    volume_frac : with a working volume (the decoder's ``stripe_range``), an offset counts as
        inside when it keeps at least this fraction of the region's pixels within the stripes they
        can see there (:func:`index_regions`).
    link_slope_unmeasured : such a component is not linked either when fewer than
        ``_SLOPE_MIN_VOTES`` of its votes have a measurable slope on both sides (the reported
        surface is a strip too thin to measure, or the component is): the test that guards the
        contact cannot run.  Found by sweeping the blur: at 1.25 px a 970-px panel hanging from
        a thin strip of wall was linked 8 stripes off (its one marker fits both offsets); the
        rule takes the sweep's wrong non-edge pixels 688 -> 0 at that blur for 0.05-0.16 points
        of coverage at every blur of 1-3 px.
    link_grad_tol, link_grad_z, link_grad_rows : the gradient test of :func:`link_components`
        for a component of more than ``link_hang_rows`` rows whose agreeing votes come from
        fewer than ``link_slope_below_rows`` rows and none along a row (it touches the reported
        pixels at its top or bottom rows only: a horizontal contact) and which shows fewer than
        ``min_markers`` marker stripes of its own at the linked offset.  At such a contact two
        surfaces' stripes line up for an even shift and their slopes along the row may match as
        well; the column's gradient along the stripes (``d column / d v``, over
        ``link_grad_rows`` rows each side of the contact) then still changes with the surface's
        tilt.  The component is not linked when the median change exceeds ``link_grad_tol`` px
        per row with a z-score over ``link_grad_z`` (``link_grad_tol=0`` disables), unless its
        contacts above and below differ with opposite signs (a steady change: one curved surface;
        :func:`_gradient_jumps`).  The multi-object scene's tilted panel at 140-160 mm baselines
        (its gradient -0.17 px per row, the wall's 0.00; ``scripts/sweep_decode.py --set
        baselines``, seeds 0-2): wrong non-edge pixels 1994 -> 1179 (140 mm: 483 -> 24; the rest
        is a strip of the panel welded along its rows into the wall's region).  The 48-scene sweep, the room-light frames and the blur grid
        are unchanged; the clean preset loses one correct component of a head (0.12 px per row at
        z 14: 82.12 -> 81.87 % reported), the real face in ``scripts/coverage_study.py`` one under
        a crease on two of three seeds (0.2 points).  The real face's hanging components reach
        0.11-0.26 px per row at z 5-8 (its relief): z 5 would cost it 1.0-1.4 points.
    link_grad_skip_rows : the component's gradient is taken from this many rows past the contact
        on: the along-stripe blur mixes the first rows with the surface beyond the contact, and
        their columns bend toward it.  A dim glossy panel hanging 46 rows from the wall above it
        (the moving multi-object frame 4 with ``--gloss 1,30`` and ``DecodeParams.
        envelope_follow_px``), 8 stripes off, its gradient -0.23 px per row against the wall's
        0.00, measured from the contact as about 0 and linked (667 wrong pixels); from 3 rows in
        it is refused.  0 -> 3: the 48-scene sweep, room light, clean, baselines and the 1-px
        lens unchanged, bit for bit; glossy surfaces 78.40 -> 78.39 % reported (one head frame
        -0.7 points); the blur grid at 1 / 2 / 3 px 82.60 / 81.96 / 80.31 -> 82.59 / 81.97 /
        80.31 %, 0 wrong.  It also refuses the panel the near slope test was made for (moving frame
        5 at 3 px of blur with ``boundary_fit_half`` 3: over 300 wrong pixels without either).
    link_grad_z_one : the z-score the gradient test needs of a component tied through one contact
        alone (every agreeing vote with the reported pixels on the same side: it hangs from the
        rows above or stands on the rows below); 0 (the default): its gradient must be seen to
        continue, a median change over ``link_grad_tol`` refuses it at any z-score.  A component
        tied above and below has two contacts agreeing on its offset, and keeps ``link_grad_z``
        and the exemption of a steady change.  The burden of proof lies with the one-contact
        link: nothing else confirms its offset (no markers of its own), and the lined-up weld
        it may be shows exactly such a change.  The multi-object scene at 740 mm before a wall
        at 1 138 mm (``scripts/sweep_decode.py --set layouts``): a panel fragment hanging from a
        strip of the wall, 12 stripes off, its change -0.21 px per row at z 6.3 and 8.2 on two
        renders (68 and 48 wrong pixels); components tied through one contact and linked
        rightly measured changes over 0.1 px per row at z 1.3-9.7, those tied above and below
        (the real face's, the heads' under room light) 0.11-0.42 at z 2.5-28 (twenty-ninth
        session, every sweep set).  From 10 (``link_grad_z``, the rule before) to 0: layouts
        134 -> 18 wrong off depth edges, 84.12 -> 84.09 % reported; the 48 scenes 85.12 -> 85.12
        %, clean 90.72 -> 90.69, baselines 87.07 -> 87.06, room light, mirrored and panels
        unchanged; the real face's scan on seed 1 80.2 -> 80.0 % kept; none wrong added anywhere.
    tilt_step, tilt_z, tilt_rows, tilt_window, tilt_break_rows, tilt_break_min, tilt_break_cuts :
        step 1 also cuts a row where it crosses the depth-edge line of the rows around it and the
        stripes' lean steps there (:func:`gbscan.kernels.tilt_step_cuts`).  Two surfaces whose
        stripes line up along a silhouette (an even number of stripes apart) and whose boundary
        spacings differ by less than ``spacing_ratio`` and ``bridge_ratio`` weld in the rows that
        cross it unparted: the tilted panel of the multi-object scene at 140-160 mm baselines (8
        stripes off, the panel's spacing 8 % wider than the wall's, one marker that fits both
        offsets) was welded into the wall's region along 3-7 of its rows and pieces of it were
        linked through them.  The stripes' lean differs: each located boundary is followed
        ``tilt_rows`` rows up and down (its tilt, ``d x / d v``, least squares: the panel
        0.08-0.10 camera px per row, the wall 0.00).  A junction whose own row is not parted near
        it, with at least ``tilt_break_min`` of the ``2 * tilt_break_rows`` rows around it parted
        within 3 px of its column, is cut when the median tilts of the ``tilt_window`` junctions
        either side of it differ by more than ``tilt_step`` px per row at a z-score over
        ``tilt_z`` (``tilt_step=0`` disables).  A row is parted there where step 1 ended a
        segment, and (``tilt_break_cuts``) where the spacing or bridge cut cut a junction across
        which the tilt steps by the same test: renders without supersampling part the
        silhouette's rows that way.  A face's creases step the tilt as much (0.07-0.36 px per
        row at z 6-38) but are not crossed by such a line.  ``scripts/sweep_decode.py --set
        baselines``: wrong non-edge pixels 1179 -> 0, on depth edges 230 -> 126 (reported 84.78
        -> 84.72 %: 175 mm -2.8 points, 125-140 mm up to +2.2); the 48-scene sweep 84.03 -> 84.14 %
        (7 wrong, 90 -> 94 on depth edges; the real face's renders -0.09 to +0.15 points).
        Counting every spacing or bridge cut as parting its row cost the real face 0.8 points;
        segment ends alone left the supersample-1 renders' welds (150 mm seed 0: 198 wrong).
    tilt_follow_rows : the same cut followed past the end of a slanted silhouette
        (:func:`gbscan.kernels.tilt_follow_cuts`, 0 disables).  The test above asks for
        ``tilt_break_min`` rows parted within 3 px of a junction's column; a silhouette slanting
        by 1-3 px a row leaves that column within a few rows, and where its last rows are welded
        only one side of them is parted.  So where a line of partings (segment ends, the spacing
        and bridge cuts, and the cuts above) at least ``tilt_follow_rows`` rows long, each row's
        within 4 px of the last one's, ends above (below) a welded row, the line is carried on
        into that row at its slant; of
        the junctions within 5 px of there whose tilt steps by the test above, the one whose two
        neighbours' tilts differ most is cut, and parts its row for the next: a welded run of
        rows is followed while the tilt steps.  The case: the held-out set's small sphere at 710
        mm over a wall at 1 037 mm (``scripts/sweep_decode.py --set holdout``, which it spent):
        its lower-right limb's last 8 rows cross onto the wall 32 stripes on, the two surfaces'
        columns within 2 projector px of a whole number of periods (the rows above, 3 px off,
        are parted), the sphere's stripes leaning -0.3 to -0.4 camera px a row and the wall's
        0.0; welded, they were indexed by the wall's markers (76 wrong pixels on 2 frames -> 0).
        The cuts also part near objects' silhouettes from the wall in rows the spacing left
        welded, which lets both surfaces be indexed: reported, every sweep set up (48 scenes
        85.12 -> 85.30 %, room light 92.67 -> 92.80, clean 90.68 -> 91.26, baselines 87.06 ->
        87.83, mirrored 91.71 -> 91.89, panels 89.11 -> 90.96, layouts 84.07 -> 86.14, holdout
        85.25 -> 86.26), no pixel on a wrong stripe added off depth edges.  With candidates within
        3 px of the carried line only, a cut placed 7 px off a near object's silhouette left its
        last stripe with the wall (layouts at 620 mm, 4 wrong pixels).
    retry_spacing_ratio, retry_min_px : a region of at least ``retry_min_px`` pixels whose
        markers do not fit the pattern or leave its offset ambiguous is often two surfaces welded
        along a silhouette where the boundary spacing jumps by less than ``spacing_ratio`` (the
        sphere's compressed stripes meeting the wall's, 1.33x); the decoder then unwraps again
        with its rows also cut where the spacing jumps by more than ``retry_spacing_ratio``,
        inside such regions only, and keeps that result when it indexes more pixels (0: no
        retry).  Lowering ``spacing_ratio`` itself to 1.3 everywhere cuts good surfaces too:
        ``scripts/sweep_decode.py`` 83.26 -> 82.75 % reported, wrong pixels off depth edges 13 -> 25.
    split_rows : a region of at least ``retry_min_px`` pixels whose markers do not fit the pattern
        may be two surfaces welded along a horizontal contact where their stripes line up (an
        even number of stripes apart): the rows above the contact fit one offset, the rows below
        another.  :func:`split_row` looks for the row where the region's markers split into two
        parts of at least ``split_rows`` rows, each indexed by its own markers (every test of
        :func:`index_regions`) at different offsets; the decoder then unwraps again with the
        vertical links across that row pair cut inside the region (``unwrap(sever_px=)``) and
        keeps the result when it indexes more pixels (0: never split); the parts are then
        indexed, and their rows checked against their markers, like any region.  Found at
        2560x1920 (``scripts/resample_study.py``, the multi-object scene shrunk by 4): a region
        of 46 381 shrunk px whose rows 150-293 fit offset 24 and rows 294-425 offset 48 was
        dropped whole (47.1 % of the scene reported; 82.7 % split, none wrong off depth edges).
    split_undecided : the rows a split cannot place are reported unindexed: when several cuts
        tie at the fewest mismatching pixels (:func:`split_row` with ``span``: the rows between
        them show no marker stripe of either part), the region is cut at the first and the rows
        down to the last may belong to either surface.  The multi-object scene at 800 mm with
        its wall at 1 231 mm, the panel plain (``scripts/sweep_decode.py --set layouts``): the
        wall's rows just above the box tie from 5 rows above the true contact, and 3 rows of the
        wall carried the box's offset, 12 stripes off (3 wrong pixels off the depth-edge line,
        40 on it) -> none (twenty-ninth session; the frame 63.92 -> 63.91 % reported, every other
        sweep frame unchanged).
    peel_max_frac : a region of at least ``retry_min_px`` pixels whose markers do not fit the
        pattern may be one surface with a strip of another welded in beside it, along a
        slanted silhouette that neither the row cuts nor :func:`split_row` separate.
        :func:`peel_conflicts` takes the row stretches whose own markers contradict the region's
        best offset (:func:`marker_conflicts`, as for an indexed region) out of it and scores the
        rest again: when the rest passes every test of :func:`index_regions` at the same offset
        and the stretches hold at most ``peel_max_frac`` of the region's pixels, the region is
        indexed (why ``peeled``) and the stretches are reported unindexed (0: never peel).
        Found at a 175 mm baseline (the multi-object scene): the sphere (16 000 px) welded along
        its lower right rim to 15 rows of the wall, 22 stripes apart, was dropped whole
        (mismatch 5.9 % of the evidence against ``max_mismatch`` 5 %); peeled, 71.4-71.6 ->
        82.3-82.5 % of the scene reported on seeds 0-2, none wrong.
    peel_min_markers : the marker stripes the rest must show to be indexed so (at least
        ``min_markers``): where few markers are seen, a stretch of the other surface that holds
        none contradicts nothing and stays in.  Measured with regions down to 300 px peeled: a
        face region of 885 px (3 markers seen) whose majority, 609 px, lay 4 stripes from the
        offset its markers chose was peeled of 57 px and indexed with 403 wrong pixels.
    peel_margin : the rest's runner-up offset must mismatch more than its best by this many times
        the indexing's margin (``index_margin`` / ``index_margin_events``): a region already found
        inconsistent must win clearly.  Measured over the sweep cache (lossless, JPEG q95 4:4:4
        and q90 4:2:0) and the baselines set: the regions the peel indexed right won by 1.33-4.77
        margins, the wrong ones by 1.12-1.26 (a q90 4:2:0 frame of the multi-object scene:
        2 589 px, 4 markers, every kept pixel wrong, 1 443 wrong pixels in all with its linked
        neighbours); 2 refuses every wrong one and the right one at 1.33 (JPEG).
    """

    n_ref_pixels: int = 4
    n_ref_rows: int = 3
    agree_frac: float = 0.8
    min_overlap_frac: float = 0.3
    same_frac: float = 0.75
    spacing_ratio: float = 1.35
    bridge_ratio: float = 1.15
    max_gap_px: int = 1
    spike_px: int = 1
    marker_flank_px: int = 2
    marker_end_flank: bool = True
    min_region_px: int = 150
    min_marker_px: int = 12
    min_markers: int = 2
    index_margin: float = 0.25
    index_margin_events: float = 1.5
    index_margin_stripes: int = 2
    index_strong_stripe_px: int = 60
    max_mismatch: float = 0.05
    conflict_run_px: int = 2
    conflict_events: int = 2
    conflict_clean_level: float = 0.15
    conflict_confirm: bool = True
    conflict_persist_rows: int = 3
    conflict_extend: bool = True
    conflict_grow: bool = True
    link_votes: int = 8
    link_lines: int = 3
    link_tol_px: float = 2.0
    link_agree_frac: float = 0.95
    link_gap_px: int = 2
    link_marker_frac: float = 0.05
    min_believable_junctions: int = 2
    link_rows: int = 1
    link_reach_rows: int = 8
    link_hang_rows: int = 5
    link_slope_tol: float = 0.04
    link_slope_z: float = 15.0
    link_slope_z_near: float = 10.0
    link_slope_rows: int = 4
    link_slope_half_px: int = 8
    link_slope_below_rows: int = 3
    link_slope_unmeasured: bool = True
    link_grad_tol: float = 0.1
    link_grad_z: float = 10.0
    link_grad_rows: int = 6
    link_grad_skip_rows: int = 3
    link_grad_z_one: float = 0.0
    tilt_step: float = 0.03
    tilt_z: float = 6.0
    tilt_rows: int = 6
    tilt_window: int = 4
    tilt_break_rows: int = 10
    tilt_break_min: int = 10
    tilt_break_cuts: bool = True
    tilt_follow_rows: int = 8
    volume_frac: float = 0.5
    retry_spacing_ratio: float = 1.2
    retry_min_px: int = 1000
    split_rows: int = 3
    split_undecided: bool = True
    peel_max_frac: float = 0.25
    peel_min_markers: int = 4
    peel_margin: float = 2.0

    def __post_init__(self):
        for name in ("n_ref_pixels", "n_ref_rows", "min_region_px", "min_markers", "conflict_run_px",
                     "conflict_events"):
            if int(getattr(self, name)) < 1:
                raise GBError(f"UnwrapParams.{name} must be >= 1, got {getattr(self, name)}")
        if not 0.5 <= float(self.agree_frac) <= 1.0:
            raise GBError(f"UnwrapParams.agree_frac must be in [0.5, 1], got {self.agree_frac}")
        if int(self.max_gap_px) < 0 or int(self.spike_px) < 0 or int(self.marker_flank_px) < 0:
            raise GBError(f"UnwrapParams.max_gap_px, spike_px and marker_flank_px must be >= 0, got "
                          f"{self.max_gap_px}, {self.spike_px}, {self.marker_flank_px}")
        if int(self.conflict_persist_rows) < 0 or int(self.conflict_persist_rows) == 1:
            raise GBError(f"UnwrapParams.conflict_persist_rows must be 0 (off) or >= 2, got "
                          f"{self.conflict_persist_rows}")
        if int(self.link_votes) < 0 or int(self.link_lines) < 1 or int(self.link_gap_px) < 0:
            raise GBError("UnwrapParams.link_votes and link_gap_px must be >= 0, link_lines >= 1")
        if not float(self.index_margin_events) >= 0:
            raise GBError(f"UnwrapParams.index_margin_events must be >= 0 (0: the fixed index_margin only), got "
                          f"{self.index_margin_events}")
        if int(self.index_strong_stripe_px) < 0:
            raise GBError(f"UnwrapParams.index_strong_stripe_px must be >= 0 (0: never), got "
                          f"{self.index_strong_stripe_px}")
        if int(self.index_margin_stripes) < 0:
            raise GBError(f"UnwrapParams.index_margin_stripes must be >= 0 (0: the pixel margin alone), got "
                          f"{self.index_margin_stripes}")
        if int(self.link_hang_rows) < 0:
            raise GBError(f"UnwrapParams.link_hang_rows must be >= 0 (0 disables), got {self.link_hang_rows}")
        if not float(self.link_grad_z_one) >= 0:
            raise GBError(f"UnwrapParams.link_grad_z_one must be >= 0 (0: a one-contact component's gradient "
                          f"change is judged by its size alone), got {self.link_grad_z_one}")
        if int(self.link_grad_skip_rows) < 0:
            raise GBError(f"UnwrapParams.link_grad_skip_rows must be >= 0 (0: from the contact row), got "
                          f"{self.link_grad_skip_rows}")
        if not float(self.tilt_step) >= 0 or not float(self.tilt_z) >= 0 or int(self.tilt_rows) < 2 \
                or int(self.tilt_window) < _TILT_MIN_SIDE or int(self.tilt_break_rows) < 1 \
                or not 0 <= int(self.tilt_break_min) <= 2 * int(self.tilt_break_rows):
            raise GBError(f"UnwrapParams.tilt_step and tilt_z must be >= 0 (tilt_step 0 disables), tilt_rows >= 2, "
                          f"tilt_window >= {_TILT_MIN_SIDE}, tilt_break_rows >= 1 and tilt_break_min in 0 .. "
                          f"2 * tilt_break_rows, got {self.tilt_step}, {self.tilt_z}, {self.tilt_rows}, "
                          f"{self.tilt_window}, {self.tilt_break_rows}, {self.tilt_break_min}")
        if int(self.tilt_follow_rows) < 0:
            raise GBError(f"UnwrapParams.tilt_follow_rows must be >= 0 (0: no silhouette is followed past its "
                          f"end), got {self.tilt_follow_rows}")
        if not float(self.link_grad_tol) >= 0 or not float(self.link_grad_z) >= 0 or int(self.link_grad_rows) < 2:
            raise GBError(f"UnwrapParams.link_grad_tol and link_grad_z must be >= 0 (link_grad_tol 0 disables) and "
                          f"link_grad_rows >= 2, got {self.link_grad_tol}, {self.link_grad_z}, {self.link_grad_rows}")
        if int(self.min_believable_junctions) < 0 or int(self.link_rows) < 1 or int(self.link_reach_rows) < 0:
            raise GBError(f"UnwrapParams.min_believable_junctions and link_reach_rows must be >= 0, link_rows >= 1, "
                          f"got {self.min_believable_junctions}, {self.link_reach_rows}, {self.link_rows}")
        if float(self.link_slope_tol) < 0 or float(self.link_slope_z) < 0 or int(self.link_slope_rows) < 1 \
                or int(self.link_slope_half_px) < 1 or int(self.link_slope_below_rows) < 0 \
                or float(self.link_slope_z_near) < 0:
            raise GBError(f"UnwrapParams.link_slope_tol, link_slope_z and link_slope_z_near must be >= 0 (tol 0 "
                          f"disables the slope test), link_slope_rows and link_slope_half_px >= 1, "
                          f"link_slope_below_rows >= 0, got {self.link_slope_tol}, {self.link_slope_z}, "
                          f"{self.link_slope_z_near}, {self.link_slope_rows}, {self.link_slope_half_px}, "
                          f"{self.link_slope_below_rows}")
        if not (float(self.retry_spacing_ratio) == 0.0 or float(self.retry_spacing_ratio) > 1.0):
            raise GBError(f"UnwrapParams.retry_spacing_ratio must be > 1 (a spacing factor) or 0 (no retry), got "
                          f"{self.retry_spacing_ratio}")
        if int(self.retry_min_px) < 1:
            raise GBError(f"UnwrapParams.retry_min_px must be >= 1, got {self.retry_min_px}")
        if int(self.split_rows) < 0:
            raise GBError(f"UnwrapParams.split_rows must be >= 0 (0: never split a region), got {self.split_rows}")
        if not float(self.peel_margin) >= 1.0:
            raise GBError(f"UnwrapParams.peel_margin must be >= 1 (times the indexing's margin), got "
                          f"{self.peel_margin}")
        if int(self.peel_min_markers) < 1:
            raise GBError(f"UnwrapParams.peel_min_markers must be >= 1, got {self.peel_min_markers}")
        if not 0.0 <= float(self.peel_max_frac) < 1.0:
            raise GBError(f"UnwrapParams.peel_max_frac must be in [0, 1) (0: never peel a region), got "
                          f"{self.peel_max_frac}")
        if not (float(self.bridge_ratio) == 0.0 or float(self.bridge_ratio) > 1.0):
            raise GBError(f"UnwrapParams.bridge_ratio must be > 1 (a spacing factor) or 0 (disabled), got "
                          f"{self.bridge_ratio}")
        if not 0.0 <= float(self.conflict_clean_level) < 1.0:
            raise GBError(f"UnwrapParams.conflict_clean_level must be in [0, 1) (0 disables), got "
                          f"{self.conflict_clean_level}")
        if not 0.0 < float(self.volume_frac) <= 1.0:
            raise GBError(f"UnwrapParams.volume_frac must be in (0, 1], got {self.volume_frac}")
        if not (0 < float(self.link_tol_px) < 4.0) or not 0.5 <= float(self.link_agree_frac) <= 1.0:
            raise GBError(f"UnwrapParams.link_tol_px must be in (0, 4) px (a quarter period: 2) and link_agree_frac "
                          f"in [0.5, 1], got {self.link_tol_px}, {self.link_agree_frac}")


@dataclass
class Segments:
    """Step-1 result.  Per pixel: ``seg`` (H, W) int32 (-1 none), ``rel`` (H, W) int32.
    Per segment (numbered row by row, left to right): ``row, u0, u1`` (inclusive span),
    ``j0, j1`` (junction range), ``parity`` (1 if colour fixed the parity).
    Per junction (boundary between consecutive runs): ``j_seg, j_ua, j_ub, j_la, j_lb, j_rel``
    (``j_rel`` = relative index of the stripe right of the boundary = relative boundary index),
    ``j_x`` its sub-pixel camera position (float32, NaN if not located; None if not computed).
    """

    seg: np.ndarray
    rel: np.ndarray
    row: np.ndarray
    u0: np.ndarray
    u1: np.ndarray
    j0: np.ndarray
    j1: np.ndarray
    parity: np.ndarray
    j_seg: np.ndarray
    j_ua: np.ndarray
    j_ub: np.ndarray
    j_la: np.ndarray
    j_lb: np.ndarray
    j_rel: np.ndarray
    j_x: np.ndarray | None = None  # sub-pixel camera position of each junction (when known)
    # the tilt-step cut's tracks and tests on these junctions (_tilt_cut_mask: kept for the
    # decoder's retries, which unwrap the same step-1 segments again)
    tilt_memo: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def n(self) -> int:
        return int(self.row.shape[0])


@dataclass
class Edges:
    """Step-2 result: segment ``s`` (row v) and ``t`` (row v-1), winning ``offset``
    (``rel_t - rel_s``), ``n_agree`` votes for it, ``n_same`` same-colour votes in all,
    ``n_overlap`` labelled pixel pairs, ``len_min`` the shorter segment's length."""

    s: np.ndarray
    t: np.ndarray
    offset: np.ndarray
    n_agree: np.ndarray
    n_same: np.ndarray
    n_overlap: np.ndarray
    len_min: np.ndarray | None = None

    def strong(self, p: UnwrapParams) -> np.ndarray:
        """Enough agreeing votes, a high agreeing fraction, fewer than ``n_ref_pixels`` dissenters,
        and agreeing votes over at least ``min_overlap_frac`` of the shorter segment (at a depth
        edge two surfaces overlap on a few pixels only, where stripes may line up by chance)."""
        dissent = self.n_same - self.n_agree
        ok = ((self.n_agree >= p.n_ref_pixels) & (self.n_agree >= p.agree_frac * self.n_same)
              & (dissent < p.n_ref_pixels))
        if self.len_min is not None:
            ok &= self.n_agree >= p.min_overlap_frac * self.len_min
        # colours kept from row to row: across a depth edge the stripes are shifted and many
        # vertically adjacent pixels change colour even when the votes happen to agree
        ok &= self.n_same >= p.same_frac * self.n_overlap
        return ok

    def disputed(self, p: UnwrapParams) -> np.ndarray:
        """At least ``n_ref_pixels`` same-colour votes dissent from the winning offset: part of one
        of the two segments is shifted (an inserted or lost stripe, or another surface)."""
        return (self.n_same - self.n_agree) >= p.n_ref_pixels


@dataclass
class Unwrapped:
    """Result of :func:`unwrap`.

    relative : (H, W) int32 stripe index consistent within a region (meaningless where region < 0).
    region : (H, W) int32 region id 0..n-1, -1 where the pixel is in no kept region.
    inconsistent : (H, W) bool pixels flagged by step 7.
    segments, edges : the step-1/2 tables; ``seg_region`` (n_seg,) region per segment (-1),
    ``seg_P`` (n_seg,) int32 potential (``relative = rel + seg_P[seg]``).
    stats : counts (segments, believable, regions found/kept, conflicts).
    """

    relative: np.ndarray
    region: np.ndarray
    inconsistent: np.ndarray
    segments: Segments
    edges: Edges
    seg_region: np.ndarray
    seg_P: np.ndarray
    region_px: np.ndarray
    region_conflicts: np.ndarray
    believable: np.ndarray
    isolated: np.ndarray
    stats: dict = field(default_factory=dict)
    seg_root: np.ndarray | None = None  # (n_seg,) int32 union-find root of every segment (components)


# -- step 1 -------------------------------------------------------------------------------------
def unroll_rows(labels: np.ndarray, max_gap_px: int = 1, spike_px: int = 1, marker_flank_px: int = 2,
                marker_end_flank: bool = True) -> Segments:
    """Step 1, *unroll each row by transitions along it*.

    ``labels`` (H, W) uint8.  Along each row, runs of one colour are chained while consecutive
    colours differ and are adjacent (or separated by at most ``max_gap_px`` unlabelled pixels);
    each colour change is one stripe boundary (+1 to the relative index).  Parity is fixed by
    colour: a green run must get an even index, a blue one odd; a contradiction (``G C B``: a
    marker is always flanked by equal colours) ends the segment.  Runs of at most ``spike_px``
    pixels between two runs of one colour are noise and are absorbed, and runs of at most
    ``marker_flank_px`` pixels that make a marker's flanks disagree (``X Y C X``) are the mixed
    pixels of a flank and the marker (see :func:`gbscan.kernels.row_segments`); with
    ``marker_end_flank`` also a 1 px run between a marker and the end of its stretch (``. Y C X``).
    """
    from . import kernels

    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    out = kernels.row_segments(labels, int(max_gap_px), int(spike_px), int(marker_flank_px), bool(marker_end_flank))
    return Segments(*out)


# -- step 2 -------------------------------------------------------------------------------------
def relate_rows(labels: np.ndarray, segs: Segments) -> Edges:
    """Step 2, *unroll every row by relation with the upper neighbour row*.

    Every pixel whose upper neighbour carries the same colour votes for the offset between the
    two segments' relative indices (stripes are near-vertical, so most same-colour vertical
    neighbours lie on the same stripe; pixels next to a boundary that shifts between rows
    differ in colour and do not vote).  Returns one edge per overlapping pair, with the winning
    offset and the vote counts (sorted by the lower segment ``s``).
    """
    from . import kernels

    n = max(segs.n, 1)
    e = kernels.vertical_votes(np.ascontiguousarray(labels, dtype=np.uint8), segs.seg, segs.rel, n)
    length = (segs.u1 - segs.u0 + 1).astype(np.int32)
    len_min = np.minimum(length[e[0]], length[e[1]]) if segs.n else np.zeros(0, np.int32)
    return Edges(*e, len_min=len_min)


# -- step 3 -------------------------------------------------------------------------------------
def believable_segments(segs: Segments, edges: Edges, p: UnwrapParams, *, strong=None) -> np.ndarray:
    """Step 3, *determine believable rows*: (n_seg,) bool.

    A segment is believable when it is linked by strong edges (enough agreeing votes, few
    dissenting ones) into a vertical chain covering at least ``n_ref_rows`` rows, it saw a green
    or blue run (parity known), and none of its edges to the row above or below is a strong
    disagreement (an edge with many votes but a low agreement fraction means part of the segment
    is shifted: an inserted or lost stripe) -- :meth:`Edges.disputed` -- and it holds at least
    ``min_believable_junctions`` stripe boundaries.  ``strong`` (optional): ``edges.strong(p)``.
    """
    from . import kernels

    if strong is None:
        strong = edges.strong(p)
    chain = kernels.chain_lengths(segs.n, edges.s, edges.t, strong)
    ok = (chain >= p.n_ref_rows) & (segs.parity > 0)
    # a segment with fewer than ``min_believable_junctions`` boundaries holds no complete stripe:
    # a chain of such bits can weld two surfaces at a horizontal depth edge (they stay doubtful:
    # step 6 attaches each to at most one region, never merging two)
    ok &= (segs.j1 - segs.j0) >= p.min_believable_junctions
    bad_edge = edges.disputed(p)
    disputed = np.zeros(segs.n, bool)
    disputed[edges.s[bad_edge]] = True
    disputed[edges.t[bad_edge]] = True
    return ok & ~disputed


# -- steps 4 and 6 ------------------------------------------------------------------------------
def _edge_order(edges: Edges) -> np.ndarray:
    # strongest first: most agreeing votes, then fewest dissenting ones (the lexsort
    # ``np.lexsort((n_same - n_agree, -n_agree))``, compiled)
    from . import kernels

    return kernels.edge_order(edges.n_agree, edges.n_same)


def link_believable(segs: Segments, edges: Edges, believable: np.ndarray, p: UnwrapParams, *, strong=None,
                    order=None):
    """Step 4, *unroll each pixel by relation with its upper neighbour in believable rows*.

    Two stages, so that one lucky row pair never welds two surfaces together (at a horizontal
    depth edge the stripes of the far and the near surface may happen to line up):

    a. *strips*: a believable segment is linked to the one above when each is the other's best
       strong edge (mutual best match); strips are vertical chains of segments on one surface.
    b. strips are merged when at least ``n_ref_rows`` distinct edges between them agree on the
       relative offset and at least ``agree_frac`` of all their strong edges do; pairs with the
       most support first; an edge contradicting what is already fixed is a conflict.

    Every pixel of a region then gets ``rel + P[segment]``, consistent with its upper neighbour.
    Returns the union-find state ``(parent, pot, size, conflicts)``.  ``strong`` and ``order``
    (optional): ``edges.strong(p)`` and :func:`_edge_order` when the caller has them.
    """
    from . import kernels

    n = segs.n
    parent = np.arange(n, dtype=np.int32)
    pot = np.zeros(n, np.int32)
    size = np.ones(n, np.int32)
    conflicts = np.zeros(n, np.int32)
    if strong is None:
        strong = edges.strong(p)
    strong = strong & believable[edges.s] & believable[edges.t]
    # both stages in one kernel (mutual best edges, then the strips' (pair, offset) consensus)
    kernels.link_strips(parent, pot, size, conflicts, edges.s, edges.t, edges.offset, edges.n_agree, edges.n_same,
                        _edge_order(edges) if order is None else order, strong, believable,
                        int(p.n_ref_rows), float(p.agree_frac))
    return parent, pot, size, conflicts


def split_doubtful(labels: np.ndarray, segs: Segments, believable: np.ndarray, p: UnwrapParams) -> Segments:
    """Step 5, *unroll each row by transitions again*.

    A doubtful (non-believable) segment is walked again run by run; each run's majority
    relation (segment, offset) to the row above and to the row below is compared with the
    previous run's: where it changes, the transition between the two runs is not trusted and the
    segment is cut there (an inserted or lost stripe shifts the rest of the row by two; a
    segment may also bridge two surfaces).  The pieces keep their relative indices and become
    segments of their own.  Believable segments are unchanged.
    """
    from . import kernels

    doubtful = ~believable
    if segs.n == 0 or not doubtful.any():
        return segs
    lab = np.ascontiguousarray(labels, dtype=np.uint8)
    cut = kernels.cut_junctions(lab, segs.seg, segs.rel, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.j_ua,
                                segs.j_ub, doubtful)
    if not cut.any():
        return segs
    return _apply_cuts(segs, cut)


_NO_JX = np.empty(0, np.float32)   # _apply_cuts' j_x where the segments have none


def _apply_cuts(segs: Segments, cut: np.ndarray) -> Segments:
    """Split segments at the transitions flagged in ``cut`` (one kernel, shared by the cutters)."""
    from . import kernels

    j_x = _NO_JX if segs.j_x is None else segs.j_x
    r = kernels.apply_cuts(segs.seg, segs.row, segs.u0, segs.u1, segs.j0, segs.j1, segs.parity, segs.j_seg,
                           segs.j_ua, segs.j_ub, segs.j_la, segs.j_lb, cut, segs.j_rel, j_x)
    return Segments(r[0], segs.rel, r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], r[9], r[10], r[11], r[13],
                    None if segs.j_x is None else r[14])


def cut_depth_edges(segs: Segments, ratio: float) -> Segments:
    """Step 1 (geometry check of the transitions): cut segments where the boundary spacing jumps.

    A row crossing a depth edge may show a perfectly valid colour sequence while the stripe index
    jumps by many stripes; the spacing of the located boundaries (``segs.j_x``) changes abruptly
    there (another surface, another distance and slant).  Cutting there keeps each segment on one
    surface; the pieces are related to their neighbour rows like any segment.
    """
    cut = _spacing_cut_mask(segs, ratio)
    return segs if cut is None else _apply_cuts(segs, cut)


def _spacing_cut_mask(segs: Segments, ratio: float):
    """(n_junctions,) uint8 junctions :func:`cut_depth_edges` cuts, None when it cuts none."""
    from . import kernels

    if segs.j_x is None or ratio <= 0 or segs.j_seg.size == 0:
        return None
    cut = kernels.spacing_cuts(segs.j_x.astype(np.float64), segs.j0, segs.j1, float(ratio))
    return cut if cut.any() else None


def cut_unlocated(segs: Segments, ratio: float) -> Segments:
    """Step 1 (geometry check where it is blind): cut segments at unlocated boundaries whose
    bridge does not fit the spacing.

    :func:`cut_depth_edges` compares the spacings of *located* boundaries; a boundary whose
    crossing the sub-pixel locator cannot find (``segs.j_x`` NaN: the runs' colours do not cross
    cleanly, e.g. two surfaces meeting) interrupts that comparison, and a row crossing a
    silhouette there keeps one segment even when the two surfaces' stripes are many stripes
    apart.  A run of unlocated boundaries stays inside its segment only when the located
    boundaries either side of it bridge it with the spacing of the row on both sides (within
    ``ratio``, :func:`gbscan.kernels.bridge_cuts`); otherwise the segment is cut at each of them
    and each side is related to its neighbour rows on its own.
    """
    cut = _unlocated_cut_mask(segs, ratio)
    return segs if cut is None else _apply_cuts(segs, cut)


def _unlocated_cut_mask(segs: Segments, ratio: float, pre=None):
    """(n_junctions,) uint8 junctions :func:`cut_unlocated` cuts (after the junctions ``pre`` are
    cut, e.g. by :func:`cut_depth_edges`: they end a piece; not included), None when none."""
    from . import kernels

    if segs.j_x is None or ratio <= 0 or segs.j_seg.size == 0 or not np.isnan(segs.j_x).any():
        return None
    if pre is None:
        pre = np.zeros(segs.j_seg.size, np.uint8)
    cut = kernels.bridge_cuts(segs.j_x.astype(np.float64), segs.j0, segs.j1, float(ratio), pre)
    return cut if cut.any() else None


def _tilt_cut_mask(segs: Segments, shape, p: "UnwrapParams", pre=None):
    """(n_junctions,) uint8 junctions where a row crosses the depth-edge line of the rows around
    it and the boundaries' tilt steps there (``p.tilt_step``, :func:`gbscan.kernels.tilt_step_cuts`;
    ``pre``: the junctions the spacing and bridge cuts cut, which part rows too where the tilt
    steps across them, with ``p.tilt_break_cuts``), None when it cuts none."""
    from . import kernels

    H, W = shape
    if segs.j_x is None or p.tilt_step <= 0 or segs.j_seg.size == 0:
        return None
    # the tracks and tests done, kept on the segments: the decoder's retries unwrap the same
    # step-1 segments (and positions) again
    memo = segs.tilt_memo
    key = (int(p.tilt_rows), int(p.tilt_window), float(p.tilt_step), float(p.tilt_z))
    if memo is None or memo[0] != key or memo[1] is not segs.j_x:
        n = segs.j_seg.size
        memo = (key, segs.j_x, np.full(n, np.nan), np.zeros(n, np.uint8), np.zeros(n, np.uint8))
        segs.tilt_memo = memo
    cut = kernels.tilt_step_cuts(segs.j_x, segs.j_seg, segs.row, segs.u0, segs.u1, segs.j0,
                                 segs.j1, segs.j_ua, segs.j_la, segs.j_lb, int(H), int(W), int(p.tilt_rows),
                                 _TILT_TRACK_PX, int(p.tilt_break_rows), _TILT_BREAK_PX, int(p.tilt_break_min),
                                 int(p.tilt_window), _TILT_MIN_SIDE, float(p.tilt_step), float(p.tilt_z),
                                 _TILT_NOISE_FLOOR, pre if pre is not None and p.tilt_break_cuts else _NO_JUNCTIONS,
                                 *memo[2:])
    if p.tilt_follow_rows > 0:
        cut |= kernels.tilt_follow_cuts(segs.j_x, segs.j_seg, segs.row, segs.u0, segs.u1, segs.j0, segs.j1,
                                        segs.j_ua, segs.j_la, segs.j_lb, int(H), int(W), int(p.tilt_rows),
                                        _TILT_TRACK_PX, _TILT_BREAK_PX, int(p.tilt_window), _TILT_MIN_SIDE,
                                        float(p.tilt_step), float(p.tilt_z), _TILT_NOISE_FLOOR,
                                        int(p.tilt_follow_rows), cut, pre if pre is not None else _NO_JUNCTIONS,
                                        *memo[2:])
    return cut if cut.any() else None


_NO_JUNCTIONS = np.zeros(0, np.uint8)
_TILT_TRACK_PX = 1.0     # a boundary is followed to the next row's nearest one within this (camera px)
_TILT_BREAK_PX = 3       # a segment end this close (camera px) to a junction's column counts as a break there
_TILT_MIN_SIDE = 3       # finite tilts each side of a junction the tilt-step test needs
_TILT_NOISE_FLOOR = 0.01  # smallest spread (px per row) assumed of a side's boundary tilts


def attach_doubtful(segs: Segments, edges: Edges, believable: np.ndarray, state, p: UnwrapParams, *, strong=None,
                    order=None):
    """Step 6, *unroll every row by relation with the upper neighbour* (and the lower one).

    Each doubtful segment (piece) joins at most one region, through its strongest strong edge
    to a believable segment; further edges only check it (a disagreement is a conflict).  Two
    regions are never merged through a doubtful segment.  Updates ``state`` in place.
    ``strong``, ``order`` (optional): ``edges.strong(p)`` and :func:`_edge_order` when at hand.
    """
    from . import kernels

    parent, pot, size, conflicts = state
    use = (edges.strong(p) if strong is None else strong) & (believable[edges.s] != believable[edges.t])
    kernels.link_segments(parent, pot, size, conflicts, edges.s, edges.t, edges.offset,
                          _edge_order(edges) if order is None else order, use, believable, True)
    return state


# -- step 7 -------------------------------------------------------------------------------------
def check_pixels(labels: np.ndarray, relative: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Step 7, *unroll each pixel by relation with its upper neighbour*: (H, W) bool flags.

    A pixel is flagged when its upper or lower neighbour has the same colour and the same
    region but a different index (stripes are continuous across rows).
    """
    from . import kernels

    return kernels.check_vertical(np.ascontiguousarray(labels, dtype=np.uint8),
                                  np.ascontiguousarray(relative, dtype=np.int32),
                                  np.ascontiguousarray(region, dtype=np.int32))


# -- the seven steps together -------------------------------------------------------------------
def _sever(edges: Edges, segs: Segments, sever_px: np.ndarray | None) -> Edges:
    """``edges`` without those whose lower segment has a pixel in ``sever_px`` (H, W) bool."""
    if sever_px is None or edges.s.size == 0:
        return edges
    hit = np.zeros(segs.n + 1, bool)
    hit[segs.seg[sever_px]] = True          # (no segment: -1 -> the last entry)
    keep = ~hit[edges.s]
    if keep.all():
        return edges
    return Edges(*(None if a is None else a[keep] for a in (edges.s, edges.t, edges.offset, edges.n_agree,
                                                             edges.n_same, edges.n_overlap, edges.len_min)))


def unwrap(labels: np.ndarray, params: UnwrapParams = UnwrapParams(), locate=None,
           retry_px: np.ndarray | None = None, segments1: Segments | None = None,
           sever_px: np.ndarray | None = None) -> Unwrapped:
    """The paper's seven steps on a colour-class image ``labels`` (H, W) uint8 -> :class:`Unwrapped`.

    ``locate`` (optional): a function ``Segments -> (n_junctions,) float32`` sub-pixel boundary
    positions (the decoder passes its own); with it, step 1 also cuts rows at depth edges
    (:func:`cut_depth_edges`, :func:`cut_unlocated`, and where a row crosses a line the rows
    around it were parted at with the stripes' lean stepping there: ``UnwrapParams.tilt_step``)
    and the positions travel with the segments
    (``segments.j_x``).  ``retry_px`` (optional, (H, W) bool, with ``locate``): rows are also cut
    where the boundary spacing jumps by more than ``params.retry_spacing_ratio`` at a boundary
    whose left pixel is in it (the decoder's retry of welded regions, see :class:`UnwrapParams`).
    ``segments1`` (optional): step 1's segments of these same labels and parameters from an
    earlier call (the retry), reused instead of recomputed; they are not modified.
    ``sever_px`` (optional, (H, W) bool): a segment with a pixel in it is never related to the row
    above (its step-2 edges upwards are dropped): the decoder's split of a welded region at a
    contact row (:func:`split_row`).
    """
    labels = np.asarray(labels)
    if labels.ndim != 2 or labels.dtype != np.uint8:
        raise GBError(f"unwrap: labels must be a 2-D uint8 array, got {labels.dtype} {labels.shape}")
    p = params
    segs1 = segments1 if segments1 is not None else \
        unroll_rows(labels, p.max_gap_px, p.spike_px, p.marker_flank_px, p.marker_end_flank)      # 1
    if locate is not None:
        segs1.j_x = np.asarray(locate(segs1), dtype=np.float32)
        # cut_depth_edges, then cut_unlocated on its pieces, and the tilt steps at the depth-edge
        # lines of the rows around: the masks, one split (_apply_cuts copies every table: ~1 ms a frame)
        c_depth = _spacing_cut_mask(segs1, p.spacing_ratio)
        if retry_px is not None and p.retry_spacing_ratio > 0:
            c_weak = _spacing_cut_mask(segs1, p.retry_spacing_ratio)
            if c_weak is not None:
                c_weak &= np.asarray(retry_px, bool)[segs1.row[segs1.j_seg], segs1.j_ua].astype(np.uint8)
                c_depth = c_weak if c_depth is None else (c_depth | c_weak)
                c_depth = c_depth if c_depth.any() else None
        c_unloc = _unlocated_cut_mask(segs1, p.bridge_ratio, c_depth)
        pre = c_depth if c_unloc is None else (c_unloc if c_depth is None else c_depth | c_unloc)
        c_tilt = _tilt_cut_mask(segs1, labels.shape, p, pre)
        n_depth_cuts = int(c_depth.sum()) if c_depth is not None else 0
        n_unlocated_cuts = int(c_unloc.sum()) if c_unloc is not None else 0
        n_tilt_cuts = int(c_tilt.sum()) if c_tilt is not None else 0
        if c_tilt is not None:
            c_depth = c_tilt if c_depth is None else (c_depth | c_tilt)
        if c_depth is not None or c_unloc is not None:
            cut = c_depth if c_unloc is None else (c_unloc if c_depth is None else c_depth | c_unloc)
            segs1 = _apply_cuts(segs1, cut)
    else:
        n_depth_cuts = n_unlocated_cuts = n_tilt_cuts = 0
    if sever_px is not None:
        sever_px = np.asarray(sever_px, bool)
        if sever_px.shape != labels.shape:
            raise GBError(f"unwrap: sever_px must be a {labels.shape} bool array, got {sever_px.shape}")
    edges1 = _sever(relate_rows(labels, segs1), segs1, sever_px)          # 2
    strong1 = edges1.strong(p)
    bel1 = believable_segments(segs1, edges1, p, strong=strong1)          # 3
    segs = split_doubtful(labels, segs1, bel1, p)                         # 5 (pieces)
    if segs is not segs1:
        edges = _sever(relate_rows(labels, segs), segs, sever_px)
        strong = edges.strong(p)
        bel = believable_segments(segs, edges, p, strong=strong)
    else:
        edges, strong, bel = edges1, strong1, bel1
    order = _edge_order(edges)   # (steps 4 and 6 take the same edges strongest first)
    state = link_believable(segs, edges, bel, p, strong=strong, order=order)   # 4
    attach_doubtful(segs, edges, bel, state, p, strong=strong, order=order)    # 6
    from . import kernels

    parent, pot, size, conflicts = state
    root, P = kernels.resolve_roots(parent, pot)
    H, W = labels.shape
    # region pixel counts: a region is a union-find root with at least one believable segment
    seg_px = (segs.u1 - segs.u0 + 1).astype(np.int64)
    root_px = np.bincount(root, weights=seg_px, minlength=segs.n) if segs.n else np.zeros(0)
    root_bel = np.bincount(root, weights=bel.astype(np.int64), minlength=segs.n) if segs.n else np.zeros(0)
    root_conf = np.bincount(root, weights=conflicts, minlength=segs.n) if segs.n else np.zeros(0)
    is_root = (np.arange(segs.n) == root)
    found = is_root & (root_bel > 0)
    kept = found & (root_px >= p.min_region_px)
    region_of_root = np.full(segs.n, -1, np.int32)
    region_of_root[kept] = np.arange(int(kept.sum()), dtype=np.int32)
    seg_region = region_of_root[root] if segs.n else np.zeros(0, np.int32)
    region, relative, isolated = kernels.paint_regions(segs.seg, segs.rel, seg_region.astype(np.int32),
                                                       P.astype(np.int32))
    incons = check_pixels(labels, relative, region)                      # 7
    n_reg = int(kept.sum())
    region_px = np.bincount(seg_region[seg_region >= 0], weights=seg_px[seg_region >= 0],
                            minlength=n_reg).astype(np.int64)
    stats = {
        "segments": segs1.n,
        "depth_edge_cuts": int(n_depth_cuts),
        "unlocated_cuts": int(n_unlocated_cuts),
        "tilt_cuts": int(n_tilt_cuts),
        "segments_believable": int(bel1.sum()),
        "pieces_after_split": segs.n,
        "regions_found": int(found.sum()),
        "regions_kept": n_reg,
        "regions_too_small": int((found & ~kept).sum()),
        "conflicts": int(conflicts.sum() // 2),
        "pixels_inconsistent": int(np.count_nonzero(incons)),
    }
    return Unwrapped(relative, region, incons, segs, edges, seg_region, P, region_px,
                     root_conf[kept].astype(np.int64) // 2 if segs.n else np.zeros(0, np.int64), bel, isolated, stats,
                    np.asarray(root, dtype=np.int32))


# -- absolute indexing (beyond the paper) -------------------------------------------------------
#: RegionIndex.why of a region whose best offset mismatches more than ``max_mismatch``
MISFIT = "markers do not fit the pattern"
#: RegionIndex.why of a region whose runner-up offset is not clearly worse than the best
AMBIGUOUS = "ambiguous offset"
#: RegionIndex.why of a region indexed by ``UnwrapParams.index_margin_stripes`` (its pixel margin short)
STRIPE_OK = "ok (stripe margin)"
#: RegionIndex.why of a region indexed by ``UnwrapParams.index_strong_stripe_px`` (one stripe apart, well seen)
STRONG_OK = "ok (strong stripe)"


@dataclass
class RegionIndex:
    """Result of :func:`index_regions` per region (arrays of length n_regions).

    offset : int absolute = relative + offset (valid where ``indexed``).
    indexed : bool, the offset is certain.
    markers_seen : distinct marker stripes observed.
    evidence : marker-related pixel votes (cyan seen + cyan expected) of the best offset.
    mismatch, runner_up : mismatching votes of the best and the second-best offset.
    why : str per region ("ok", "no markers in pattern", "too few markers", "ambiguous", ...).
    stripe_margin : how many more stripes every other candidate offset contradicts than the best
        (:func:`gbscan.kernels.score_offsets`; :func:`index_regions` always fills it, 0 for the
        regions it could not score; None in an index built otherwise).
    stripe_strength : for a region whose stripe margin is 1, how many contradicting pixels the
        one stripe that tells the best offset from the candidates one stripe worse shows (the
        fewest over those candidates; :func:`gbscan.kernels.score_offsets`); 0 otherwise, None in
        an index built otherwise.  ``UnwrapParams.index_strong_stripe_px`` reads it.
    """

    offset: np.ndarray
    indexed: np.ndarray
    markers_seen: np.ndarray
    evidence: np.ndarray
    mismatch: np.ndarray
    runner_up: np.ndarray
    why: list
    stripe_margin: np.ndarray | None = None
    stripe_strength: np.ndarray | None = None


#: index_regions scores the offsets in one compiled pass (kernels.score_offsets); False runs the
#: np.correlate form below it (the reference the tests compare with).
_SCORE_COMPILED = True


def _margin_px(params: UnwrapParams, evidence, seen):
    """Pixels by which the runner-up offset must mismatch more than the best: ``index_margin`` of
    the evidence, or ``index_margin_events`` marker events (evidence / (2 seen) px each) when less.
    Scalars give a float; arrays (one entry per region) an array.  The indexing computes it
    compiled, in :func:`gbscan.kernels.index_tests`; this is the readable form the tests compare
    it with."""
    ev, seen = np.broadcast_arrays(np.asarray(evidence, dtype=np.float64), np.asarray(seen))
    m = params.index_margin * ev
    if params.index_margin_events > 0:
        by_events = params.index_margin_events * ev / (2.0 * np.maximum(seen, 1))
        m = np.where(seen > 0, np.minimum(m, by_events), m)
    return float(m) if m.ndim == 0 else m


#: RegionIndex.why of a region whose best offset puts it outside the working volume
OUTSIDE = "outside the working volume"
#: RegionIndex.why of the scoring's statuses 0-2 (nothing to score)
_STATUS_WHY = ("empty region", "region too thin", "region wider than the pattern")


def _index_tests(params: UnwrapParams, status, seen, evidence, mismatch, runner_up) -> np.ndarray:
    """The indexing's tests on scored regions (arrays, one entry per region, as
    :func:`gbscan.kernels.score_offsets` returns them): (n,) int8, 0 where the region is indexed,
    else the first test it fails, in this order: 1 nothing scored (status 0-2), 2 its best
    offset outside the working volume (status 4), 3 too few markers seen, 4 the best offset
    mismatches too much (:data:`MISFIT`), 5 the runner-up is not clearly worse (:data:`AMBIGUOUS`).
    :func:`index_regions` and :func:`split_row` both decide by it."""
    from . import kernels

    # compiled (kernels.index_tests): the np.select of the five tests, with _margin_px's margin
    return kernels.index_tests(*(np.asarray(a) for a in (status, seen, evidence, mismatch, runner_up)),
                               int(params.min_markers), float(params.max_mismatch), float(params.index_margin),
                               float(params.index_margin_events))


def _index_why(code: int, status: int, seen: int, params: UnwrapParams) -> str:
    # RegionIndex.why of one region's _index_tests code
    if code == 1:
        return _STATUS_WHY[status]
    if code == 3:
        return f"too few markers ({seen} < {params.min_markers})"
    return ("ok", None, OUTSIDE, None, MISFIT, AMBIGUOUS)[code]

#: the working-volume test counts every 2nd row and column of a region (a fraction of its pixels)
_VOLUME_STEP = 2


def index_regions(labels: np.ndarray, relative: np.ndarray, region: np.ndarray, n_regions: int,
                  pattern: PatternSpec, params: UnwrapParams = UnwrapParams(),
                  stripe_range: np.ndarray | None = None) -> RegionIndex:
    """Absolute stripe offset of every region by the cyan markers (a matched filter).

    For each region, every candidate offset ``o`` (same parity as the colours: even) is scored
    with ALL of the region's pixels: a cyan pixel at relative index ``r`` agrees if stripe
    ``r + o`` is a marker, a green/blue pixel agrees if it is not; pixels that would fall outside
    the pattern disagree.  Offsets whose placement leaves the region's stripes inside the
    pattern are candidates.  The best offset is accepted only if (a) the region saw at least
    ``min_markers`` distinct marker stripes with ``min_marker_px`` pixels each, (b) its mismatch is
    at most ``max_mismatch`` of the marker evidence and (c) the runner-up mismatches by at least
    ``index_margin`` of the evidence more, or ``index_margin_events`` marker events more where
    that is less (regions seeing many markers).  Otherwise the region is *unindexed* -- never a
    guess.

    stripe_range : optional (2, H, W) float32, the absolute stripes (low, high; NaN: no bound) each
    pixel can see inside the scanner's working volume.  An offset is inside when it keeps at least
    ``volume_frac`` of the region's bounded pixels within their range
    (:func:`gbscan.kernels.region_offset_cover`).  The prior never picks the offset: the best
    candidate is the same with or without it, and a region whose best candidate lies outside is
    unindexed (:data:`OUTSIDE`); it only rules out runner-ups outside, which the margin test then
    ignores.
    The marker code repeats its gaps, so a region seeing 2-3 markers often has a runner-up 30-50
    stripes away -- over half a metre deeper at the paper's rig -- that the working volume excludes.
    """
    _same_maps("index_regions", labels=labels, relative=relative, region=region)
    n_st = pattern.n_stripes
    is_marker = pattern.is_marker()
    out = RegionIndex(np.zeros(n_regions, np.int64), np.zeros(n_regions, bool), np.zeros(n_regions, np.int64),
                      np.zeros(n_regions, np.int64), np.zeros(n_regions, np.int64), np.zeros(n_regions, np.int64),
                      ["unindexed"] * n_regions, np.zeros(n_regions, np.int64), np.zeros(n_regions, np.int64))
    if n_regions == 0:
        return out
    if not pattern.markers or not is_marker.any():
        out.why = ["no markers in the pattern (relative index only)"] * n_regions
        return out
    from . import kernels

    rmin, rmax, start, hc, hg = kernels.region_histograms(np.ascontiguousarray(labels, dtype=np.uint8),
                                                          np.ascontiguousarray(relative, dtype=np.int32),
                                                          np.ascontiguousarray(region, dtype=np.int32), n_regions)
    if stripe_range is None:
        cover, cstart, npx = np.zeros(0, np.int64), np.zeros(n_regions + 1, np.int64), np.zeros(n_regions, np.int64)
    else:
        stripe_range = np.asarray(stripe_range)
        if stripe_range.shape != (2, *region.shape) or stripe_range.dtype != np.float32:
            raise GBError(f"index_regions: stripe_range must be a (2, {region.shape[0]}, {region.shape[1]}) float32 "
                          f"array, got {stripe_range.dtype} {stripe_range.shape}")
        cover, cstart, npx = kernels.region_offset_cover(np.ascontiguousarray(region, dtype=np.int32),
                                                         np.ascontiguousarray(relative, dtype=np.int32),
                                                         stripe_range[0], stripe_range[1], rmin, rmax, n_st,
                                                         _VOLUME_STEP)
    frac = float(params.volume_frac)
    if _SCORE_COMPILED:
        status, seen, offset, evidence, mismatch, runner_up, stripes, strength = kernels.score_offsets(
            rmin, rmax, start, hc, hg, is_marker, int(params.min_marker_px), cover, cstart, npx, frac)
        out.markers_seen[:] = seen
        scored = status >= 3
        out.offset[scored], out.evidence[scored] = offset[scored], evidence[scored]
        out.mismatch[scored], out.runner_up[scored] = mismatch[scored], runner_up[scored]
        out.stripe_margin = np.where(scored, stripes, 0)
        out.stripe_strength = np.where(scored, strength, 0)
        code = _index_tests(params, status, seen, evidence, mismatch, runner_up)
        out.indexed[:] = code == 0
        out.why = [_index_why(int(code[k]), int(status[k]), int(seen[k]), params) for k in range(n_regions)]
        return out
    for k in range(n_regions):
        r0, r1 = int(rmin[k]), int(rmax[k])
        if r1 < r0:
            out.why[k] = _STATUS_WHY[0]
            continue
        span = r1 - r0 + 1
        n_c = hc[start[k]:start[k + 1]]
        n_g = hg[start[k]:start[k + 1]]
        seen = int((n_c >= params.min_marker_px).sum())
        out.markers_seen[k] = seen
        # core: relative indices with enough pixels (stray pixels beyond it only add mismatch)
        tot = n_c + n_g
        core = np.flatnonzero(tot >= params.min_marker_px)
        if core.size == 0:
            out.why[k] = _STATUS_WHY[1]
            continue
        c0, c1 = int(core[0]), int(core[-1])
        # extended pattern: pad by the region's span on both sides; outside the pattern every
        # observation mismatches.  Candidate: absolute index A of relative r0 + c0 in
        # [-2, n_st - core width + 2] (stray light may extend a region past the pattern's edge
        # stripes: those pixels are mismatches), same parity as r0 (colour fixes parity).
        pad = span
        M = np.zeros(n_st + 2 * pad, np.int64)
        M[pad:pad + n_st] = is_marker
        O = np.ones(n_st + 2 * pad, np.int64)
        O[pad:pad + n_st] = 0
        notM = 1 - M  # includes outside
        mis_all = (np.correlate(notM, n_c, mode="valid") + np.correlate(M, n_g, mode="valid")
                   + np.correlate(O, n_g, mode="valid"))
        exp_all = np.correlate(M, n_c + n_g, mode="valid")
        # stripes contradicting each candidate (cyan on a plain stripe, green/blue on a marker,
        # anything outside the pattern; min_marker_px pixels each)
        T = params.min_marker_px
        plain = 1 - M - O
        bad_all = (np.correlate(plain, (n_c >= T).astype(np.int64), mode="valid")
                   + np.correlate(M, (n_g >= T).astype(np.int64), mode="valid")
                   + np.correlate(O, (tot >= T).astype(np.int64), mode="valid"))
        # mis_all[i]: relative r0 sits at extended position i -> absolute A0 = i - pad
        A0 = np.arange(mis_all.size) - pad
        okA = (A0 + c0 >= -2) & (A0 + c1 <= n_st + 1) & ((A0 - r0) % 2 == 0)
        if not okA.any():
            out.why[k] = _STATUS_WHY[2]
            continue
        mis = mis_all[okA]
        cand = A0[okA]
        best = int(np.argmin(mis))
        b_mis = int(mis[best])
        ev = int(n_c.sum() + exp_all[okA][best])
        if npx[k]:  # candidate A of relative r0 at cover[cstart[k] + A + span]
            inside = cover[cstart[k] + cand + span] >= frac * npx[k]
        else:
            inside = np.ones(cand.size, bool)
        others = (np.arange(cand.size) != best) & inside
        big = np.iinfo(np.int64).max // 4
        second = int(mis[others].min()) if others.any() else big
        bad = bad_all[okA]
        stripes = int(bad[others].min() - bad[best]) if others.any() else big
        if stripes == 1:
            # the stripe that tells each candidate one stripe worse from the best, how well seen
            pos = np.arange(span)
            def contra_px(A):
                a = A + pos
                inside_p = (a >= 0) & (a < n_st)
                mk = np.zeros(span, bool)
                mk[inside_p] = is_marker[a[inside_p]].astype(bool)
                return np.where(~inside_p, tot, np.where(mk, n_g, n_c))
            pb = contra_px(int(cand[best]))
            weakest = [int(np.max(np.where((pc >= T) & (pb < T), pc, 0), initial=0))
                       for pc in (contra_px(int(a)) for a in cand[others & (bad == bad[best] + 1)])]
            out.stripe_strength[k] = min(weakest) if weakest else 0
        out.offset[k] = int(cand[best]) - r0
        out.evidence[k] = ev
        out.mismatch[k] = b_mis
        out.runner_up[k] = second
        out.stripe_margin[k] = stripes
        st = 3 if inside[best] else 4
        code = int(_index_tests(params, [st], [seen], [ev], [b_mis], [second])[0])
        out.indexed[k] = code == 0
        out.why[k] = _index_why(code, st, seen, params)
    return out


def marker_conflicts(labels: np.ndarray, un: Unwrapped, idx: RegionIndex, pattern: PatternSpec,
                     params: UnwrapParams = UnwrapParams(), gn: np.ndarray | None = None,
                     bn: np.ndarray | None = None) -> np.ndarray:
    """Stretches of rows in indexed regions that their own markers contradict.

    :func:`index_regions` fixes one offset per region from all of its markers.  At a horizontal
    depth edge the stripes of two surfaces may line up (stripe period in the camera barely
    depends on depth), so a row segment -- or a vertical link -- can weld a piece of the other
    surface into the region, shifted by an even number of stripes.  Its markers then sit where
    the region expects none and the region's markers fall on green/blue: along every segment, a
    stretch between agreeing markers holding ``conflict_events`` such contradictions is rejected
    (see :func:`gbscan.kernels.marker_conflicts`).  The decoder reports these pixels unindexed.
    With ``gn, bn`` (H, W) float32 (the classifier's locally normalised green and blue), a *clean*
    green/blue run on a marker stripe (median ``min(gn, bn)`` below ``conflict_clean_level``: the
    other channel dark, no missed marker) is decisive alone: a strip of another surface welded in
    where only one of its stripes meets a marker of the region.

    A cyan run that a marker's flanks enclose and that stays on its stripe for
    ``conflict_persist_rows`` rows of the region is decisive alone as well: a marker of another
    surface, welded in as a short strip at a horizontal contact.

    With ``conflict_extend`` a stretch does not stop at agreeing markers that fit its own shift
    as well; with ``conflict_grow`` the rejection passes up and down to the region's segments
    that hold no agreeing run (:func:`gbscan.kernels.grow_conflicts`; their spans are appended).

    Returns (n, 3) int32 spans ``(row, u_first, u_last)`` (inclusive; may overlap), empty for the
    pure pattern; :func:`spans_mask` turns them into an (H, W) bool image.
    """
    from . import kernels

    n_reg = int(idx.indexed.size)
    if not pattern.markers or n_reg == 0 or not idx.indexed.any():
        return np.zeros((0, 3), np.int32)
    is_marker = pattern.is_marker()
    sg = un.segments
    clean = gn is not None and bn is not None and float(params.conflict_clean_level) > 0
    no_channel = np.zeros((1, 1), np.float32)  # read only when the clean rule is on
    grow = bool(params.conflict_grow)
    agree = np.zeros(sg.n if grow else 0, np.uint8)
    spans = kernels.marker_conflicts(np.ascontiguousarray(labels, dtype=np.uint8),
                                          np.ascontiguousarray(gn, dtype=np.float32) if clean else no_channel,
                                          np.ascontiguousarray(bn, dtype=np.float32) if clean else no_channel,
                                          un.relative, sg.row, sg.u0, sg.u1, sg.j0, sg.j1, sg.j_ua, sg.j_ub,
                                          un.seg_region.astype(np.int32), idx.offset.astype(np.int64),
                                          idx.indexed.astype(np.bool_), is_marker, int(params.conflict_run_px),
                                          int(params.conflict_events),
                                          float(params.conflict_clean_level) if clean else 0.0,
                                          bool(params.conflict_confirm),
                                          np.ascontiguousarray(un.region, dtype=np.int32),
                                          int(params.conflict_persist_rows), bool(params.conflict_extend), agree)
    if not grow or spans.shape[0] == 0:
        return spans
    rejected = spans_mask(spans, labels.shape)
    grown = kernels.grow_conflicts(rejected, sg.seg, np.ascontiguousarray(un.region, dtype=np.int32), sg.row, sg.u0,
                                   sg.u1, un.seg_region.astype(np.int32), idx.indexed.astype(np.bool_), agree)
    if grown.size == 0:
        return spans
    more = np.stack([sg.row[grown], sg.u0[grown], sg.u1[grown]], axis=1).astype(np.int32)
    return np.concatenate([spans, more])


#: RegionIndex.why of a region indexed once the row stretches its markers contradict were taken out
PEELED = "peeled"


def failed_regions(idx: RegionIndex, region_px, min_px: int, whys=(MISFIT,)) -> np.ndarray:
    """(n_regions,) bool: the regions of at least ``min_px`` pixels (``region_px`` per region) that
    the indexing left unindexed for one of the reasons ``whys`` -- those the decoder gives a
    second chance (its retry with finer cuts, the split at a contact row, :func:`peel_conflicts`)."""
    px = np.asarray(region_px)
    return np.array([(not idx.indexed[k]) and idx.why[k] in whys and px[k] >= min_px
                     for k in range(int(idx.indexed.size))], bool)


def peel_conflicts(labels: np.ndarray, un: Unwrapped, idx: RegionIndex, pattern: PatternSpec,
                   params: UnwrapParams = UnwrapParams(), gn: np.ndarray | None = None,
                   bn: np.ndarray | None = None, stripe_range: np.ndarray | None = None) -> tuple:
    """Index the regions whose markers do not fit the pattern once the stretches of rows that
    contradict their best offset are taken out (``UnwrapParams.peel_max_frac``).

    For every region of at least ``retry_min_px`` pixels left unindexed as :data:`MISFIT`, the
    stretches :func:`marker_conflicts` rejects with the region taken at its best offset (``gn``,
    ``bn`` as there) are removed from it and the rest is scored again by :func:`index_regions`
    (``stripe_range`` as there).  A region is indexed when the rest passes every test at the
    *same* offset showing at least ``peel_min_markers`` marker stripes, with its runner-up
    ``peel_margin`` times the indexing's margin behind, and the stretches hold at most
    ``peel_max_frac`` of its pixels; its ``why`` becomes :data:`PEELED` and its markers seen,
    evidence, mismatch and runner-up the rest's.  The stretches
    stay in the region: the decoder's own :func:`marker_conflicts` pass, which sees the same
    segments and offset, reports them unindexed.

    Returns ``(RegionIndex, peeled)``: a new index (``idx`` itself when nothing is peeled) and
    the (n_regions,) int64 pixels taken out of each region indexed so (0 elsewhere).
    """
    n_reg = int(idx.indexed.size)
    peeled = np.zeros(n_reg, np.int64)
    frac = float(params.peel_max_frac)
    if frac <= 0 or not pattern.markers or n_reg == 0:
        return idx, peeled
    px = np.asarray(un.region_px)
    cand = failed_regions(idx, px, params.retry_min_px)
    if not cand.any():
        return idx, peeled
    forced = dataclasses.replace(idx, indexed=cand)    # the candidates, at their best offsets
    # (without conflict_extend and conflict_grow: the runs they add are no evidence either way,
    # and taking them out too left the rest too small to index: a panel of 4 400 px dropped)
    spans = marker_conflicts(labels, un, forced, pattern,
                             dataclasses.replace(params, conflict_extend=False, conflict_grow=False), gn, bn)
    if spans.size == 0:
        return idx, peeled
    # the stretches' pixels of the candidates (spans may overlap); everything else scores as -1
    lut = np.full(n_reg + 1, -1, np.int32)
    lut[:-1][cand] = np.flatnonzero(cand)
    rest = lut[un.region]                   # (region -1 -> the last entry, -1)
    out = spans_mask(spans, rest.shape) & (rest >= 0)
    gone = np.bincount(rest[out], minlength=n_reg).astype(np.int64)
    rest[out] = -1
    again = index_regions(labels, un.relative, rest, n_reg, pattern, params, stripe_range)
    margin = _margin_px(params, again.evidence, again.markers_seen)
    take = cand & again.indexed & (again.offset == idx.offset) & (gone > 0) & (gone <= frac * px) \
        & (again.markers_seen >= params.peel_min_markers) \
        & (again.runner_up - again.mismatch >= params.peel_margin * margin)
    if not take.any():
        return idx, peeled
    new = dataclasses.replace(idx, indexed=idx.indexed.copy(), markers_seen=idx.markers_seen.copy(),
                              evidence=idx.evidence.copy(), mismatch=idx.mismatch.copy(),
                              runner_up=idx.runner_up.copy(), why=list(idx.why))
    for k in np.flatnonzero(take):
        new.indexed[k] = True
        new.markers_seen[k], new.evidence[k] = again.markers_seen[k], again.evidence[k]
        new.mismatch[k], new.runner_up[k] = again.mismatch[k], again.runner_up[k]
        new.why[k] = PEELED
        peeled[k] = gone[k]
    return new, peeled


def index_by_stripes(idx: RegionIndex, params: UnwrapParams) -> RegionIndex:
    """The regions ``idx`` left :data:`AMBIGUOUS` whose stripe margin (``idx.stripe_margin``)
    reaches ``params.index_margin_stripes``, indexed (why :data:`STRIPE_OK`), and those whose
    stripe margin is one short of it with that stripe seen on at least
    ``params.index_strong_stripe_px`` pixels (``idx.stripe_strength``; why :data:`STRONG_OK`): a
    new index, or ``idx`` itself when there is none."""
    if params.index_margin_stripes <= 0 or idx.stripe_margin is None or not idx.indexed.size:
        return idx
    amb = np.array([w == AMBIGUOUS for w in idx.why], bool)
    take = amb & (idx.stripe_margin >= params.index_margin_stripes)
    strong = np.zeros_like(take)
    if params.index_strong_stripe_px > 0 and idx.stripe_strength is not None:
        strong = amb & ~take & (idx.stripe_margin == params.index_margin_stripes - 1) \
            & (idx.stripe_margin > 0) & (idx.stripe_strength >= params.index_strong_stripe_px)
    if not (take.any() or strong.any()):
        return idx
    new = dataclasses.replace(idx, indexed=idx.indexed | take | strong, why=list(idx.why))
    for k in np.flatnonzero(take).tolist():
        new.why[k] = STRIPE_OK
    for k in np.flatnonzero(strong).tolist():
        new.why[k] = STRONG_OK
    return new


def _same_maps(where: str, **maps) -> None:
    """GBError unless the (H, W) maps given by name are 2-D arrays of one shape (the compiled
    passes read every pixel of the first map's shape in the others)."""
    shapes = {k: np.shape(v) for k, v in maps.items()}
    first = next(iter(shapes.values()))
    if len(first) != 2 or any(s != first for s in shapes.values()):
        raise GBError(f"{where}: " + ", ".join(f"{k}" for k in shapes) + " must be 2-D arrays of one shape, got "
                      + ", ".join(f"{k} {s}" for k, s in shapes.items()))


def split_row(labels: np.ndarray, relative: np.ndarray, region: np.ndarray, k: int, pattern: PatternSpec,
              params: UnwrapParams = UnwrapParams(), span: bool = False):
    """The row at which region ``k``'s markers say it is two surfaces, one above the other.

    ``labels`` (H, W) uint8 colour classes, ``relative`` (H, W) int32 and ``region`` (H, W) int32
    from :func:`unwrap`.  For every row ``v`` leaving at least ``params.split_rows`` of the
    region's rows on each side, the rows up to ``v`` and the rows below it are scored apart by
    the marker matched filter of :func:`index_regions` (no working-volume prior).  Returns the
    last row of the upper part for the ``v`` where both parts pass every test of the indexing
    (markers seen, mismatch, margin) at *different* offsets, with the fewest mismatching pixels
    in all (the first such row on a tie); None when there is none (one surface whose markers
    simply do not fit, or a weld that no single row separates).  ``span``: returns (first, last)
    of the rows that tie at that fewest (first == last when one row stands out): the rows after
    the first down to the last may belong to either part, their markers say nothing of it.
    """
    from . import kernels
    from .pattern import BLUE, CYAN, GREEN

    _same_maps("split_row", labels=labels, relative=relative, region=region)
    n = int(params.split_rows)
    if n <= 0 or not pattern.markers:
        return None
    ys, xs = np.nonzero(np.asarray(region) == k)
    if ys.size == 0:
        return None
    v0 = int(ys.min())
    R = int(ys.max()) - v0 + 1
    if R < 2 * n:
        return None
    r = np.asarray(relative)[ys, xs].astype(np.int64)
    r0 = int(r.min())
    S = int(r.max()) - r0 + 1
    lab = np.asarray(labels)[ys, xs]
    cell = (ys - v0).astype(np.int64) * S + (r - r0)
    hc = np.cumsum(np.bincount(cell[lab == CYAN], minlength=R * S).reshape(R, S), axis=0)
    hg = np.cumsum(np.bincount(cell[(lab == GREEN) | (lab == BLUE)], minlength=R * S).reshape(R, S), axis=0)
    cut = np.arange(n - 1, R - n)                 # upper part: rows v0 .. v0 + cut
    m = cut.size
    # pseudo-regions 2i (upper part of cut i) and 2i + 1 (lower part), each over the region's span
    pc = np.empty((2 * m, S), np.int64)
    pg = np.empty((2 * m, S), np.int64)
    pc[0::2], pg[0::2] = hc[cut], hg[cut]
    pc[1::2], pg[1::2] = hc[-1] - hc[cut], hg[-1] - hg[cut]
    is_marker = pattern.is_marker()
    status, seen, offset, evidence, mismatch, runner_up, _, _ = kernels.score_offsets(
        np.full(2 * m, r0, np.int64), np.full(2 * m, r0 + S - 1, np.int64), np.arange(2 * m + 1, dtype=np.int64) * S,
        pc.ravel(), pg.ravel(), is_marker, int(params.min_marker_px), np.zeros(0, np.int64),
        np.zeros(2 * m + 1, np.int64), np.zeros(2 * m, np.int64), float(params.volume_frac), False)
    ok = _index_tests(params, status, seen, evidence, mismatch, runner_up) == 0
    both = ok[0::2] & ok[1::2] & (offset[0::2] != offset[1::2])
    if not both.any():
        return None
    total = np.where(both, mismatch[0::2] + mismatch[1::2], np.iinfo(np.int64).max)
    best = np.flatnonzero(total == total.min())
    if span:
        return v0 + int(cut[best[0]]), v0 + int(cut[best[-1]])
    return v0 + int(cut[best[0]])


def spans_mask(spans: np.ndarray, shape) -> np.ndarray:
    """(H, W) bool image of row spans ``(row, u_first, u_last)`` (inclusive), e.g. from
    :func:`marker_conflicts`."""
    out = np.zeros(shape, bool)
    for v, a, b in np.asarray(spans, dtype=np.int64).reshape(-1, 3):
        out[v, a:b + 1] = True
    return out


# -- indexing through neighbours (beyond the paper) ----------------------------------------------
@dataclass
class Links:
    """Result of :func:`link_components`.

    seg_region : (n_seg,) int32 region of every segment after linking (``un.seg_region`` plus the
        linked components: a linked kept region keeps its id, a linked small component gets a new
        id ``n_regions + i``).
    offset, indexed : (n_regions + n_new,) int64 absolute offset (stripes) and bool, the
        indexing's arrays extended and updated with the linked components.
    linked : (n_regions + n_new,) bool, region indexed through its neighbours.
    votes, dissent : (n_regions + n_new,) int64 agreeing and other votes of linked regions.
    stats : counts (components tried, linked, pixels linked, refused by votes / markers).
    """

    seg_region: np.ndarray
    offset: np.ndarray
    indexed: np.ndarray
    linked: np.ndarray
    votes: np.ndarray
    dissent: np.ndarray
    stats: dict


def link_components(labels: np.ndarray, un: Unwrapped, idx: RegionIndex, col_rel: np.ndarray, col_abs,
                    pattern: PatternSpec, params: UnwrapParams = UnwrapParams()) -> Links:
    """Index components that cannot be indexed alone through the reported pixels around them.

    Components are the union-find roots of the unwrapping (``un.seg_root``) whose segments are
    in no indexed region: regions too small to be kept, regions without enough markers.
    ``col_rel`` (H, W) float32 is every segment's projector column relative to its component
    (NaN none); ``col_abs`` (H, W) float32 the absolute column of the pixels that will be
    reported (NaN elsewhere; rim-pulled pixels should be left out: they bias the votes), or a
    function returning it (called only when some component has columns).

    The projector column is continuous on a surface: a candidate pixel next to reported pixels
    (vertically: the two pixels above or below; horizontally: the two nearest in its row past at
    most ``link_gap_px`` unreported pixels) predicts its absolute column by linear extrapolation
    (:func:`gbscan.kernels.link_votes`); ``prediction - relative column`` is a vote for the
    component's offset, an even number of stripes (multiples of ``2 * stripe_px`` px).  A
    component is linked when at least ``link_votes`` votes from ``link_lines`` distinct rows or
    columns agree within ``link_tol_px`` on one offset, they are at least ``link_agree_frac`` of
    all its votes (across a depth edge the continuation fails: votes scatter or sit between
    offsets), the offset keeps its stripes inside the pattern, and its colours agree with the
    markers there (at most ``link_marker_frac`` contradicting pixels).  A component hanging from
    a contact of few rows (taller than ``link_reach_rows`` with votes from fewer than
    ``link_slope_below_rows`` rows, or taller than ``link_hang_rows`` with votes from one row)
    must also show the column's slope along the row continuing, measurably (:func:`_slope_jumps`);
    one tied to the reported pixels only through fewer than ``link_slope_below_rows`` rows (no
    vote along a row) and seeing fewer than ``min_markers`` marker stripes of its own at the
    offset, its column's gradient along the stripes continuing too (:func:`_gradient_jumps`).
    Otherwise the component stays dropped: a guess is never made. Where two surfaces meet with their
    stripes lined up (an even shift) and no marker nearby, continuity cannot tell them apart: that
    is the residual risk, the same as the unwrapping's own vertical links (``link_rows`` narrows it,
    at a cost).
    """
    from . import kernels

    n_reg = int(idx.indexed.size)
    segs = un.segments
    w = float(pattern.stripe_px)
    stats = {"components_tried": 0, "components_linked": 0, "pixels_linked": 0, "refused_votes": 0,
             "refused_markers": 0, "refused_slope": 0, "refused_unmeasured": 0, "refused_gradient": 0}
    empty = Links(un.seg_region.astype(np.int32), idx.offset.astype(np.int64).copy(), idx.indexed.copy(),
                  np.zeros(n_reg, bool), np.zeros(n_reg, np.int64), np.zeros(n_reg, np.int64), stats)
    if params.link_votes <= 0 or segs.n == 0 or un.seg_root is None:
        return empty
    root = un.seg_root.astype(np.int32)
    sreg = un.seg_region
    seg_indexed = np.zeros(segs.n, bool)
    has = sreg >= 0
    seg_indexed[has] = idx.indexed[sreg[has]]
    seg_comp = np.where(seg_indexed, -1, root).astype(np.int32)
    comp, cr, n_fin = kernels.component_pixels_spans(segs.seg, seg_comp, np.ascontiguousarray(col_rel, dtype=np.float32),
                                                     segs.row, segs.u0, segs.u1)
    if n_fin == 0:
        return empty
    if callable(col_abs):
        col_abs = col_abs()
    vc, vr, vl, vv = kernels.link_votes(comp, cr, np.ascontiguousarray(col_abs, dtype=np.float32),
                                        int(params.link_gap_px))
    if vc.size == 0:
        stats["components_tried"] = 0
        return empty
    period = 2.0 * w
    k = np.round(vr / period).astype(np.int64)
    good = np.abs(vr - k * period) <= float(params.link_tol_px)
    # agreeing votes per (component, offset), their distinct lines and rows; the best offset per
    # component (one compiled group-by: kernels.best_vote_offsets)
    n_all, tried, bc, bk, bcnt, b_lines, b_rows = kernels.best_vote_offsets(
        vc, k, good, vl, vv, segs.n, int(segs.seg.shape[0]), int(segs.seg.shape[1]))
    stats["components_tried"] = int(tried)
    accept_c = np.zeros(0, np.int64)
    accept_k = accept_n = accept_c
    if bc.size:
        # rows each component spans: a tall one needs votes from ``link_rows`` rows
        height = kernels.component_row_span(seg_comp, segs.row, bc)
        tall = height > params.link_reach_rows
        ok = ((bcnt >= params.link_votes) & (b_lines >= params.link_lines)
              & ((b_rows >= params.link_rows) | ~tall)
              & (bcnt >= params.link_agree_frac * n_all[bc]))
        accept_c, accept_k, accept_n = bc[ok], bk[ok], bcnt[ok]
        acc_rows, acc_height = b_rows[ok], height[ok]
        few_rows = (tall & (b_rows < params.link_slope_below_rows))[ok] if params.link_slope_below_rows > 0 \
            else np.ones(accept_c.size, bool)
        if params.link_hang_rows > 0:
            # a shorter component hanging from one row of votes: the contact of a lined-up weld
            few_rows |= (~tall & (height > params.link_hang_rows) & (b_rows == 1))[ok]
        if params.link_slope_tol > 0 and few_rows.any():
            # across a horizontal depth edge the columns may continue (an even stripe shift) but
            # the column's slope along the row does not (another distance)
            jumps = np.zeros(accept_c.size, bool)
            jumps[few_rows], measured = _slope_jumps(
                vc[good], k[good], vl[good], vv[good], comp, cr, col_abs, un.region, accept_c[few_rows],
                accept_k[few_rows], int(params.link_slope_rows), int(params.link_slope_half_px),
                float(params.link_slope_tol), float(params.link_slope_z), return_measured=True,
                z_near=float(params.link_slope_z_near))
            # the guard cannot run: the contact is the component's only tie, and nothing tells a
            # continuing surface from a lined-up one
            blind = np.zeros(accept_c.size, bool)
            if params.link_slope_unmeasured:
                blind[few_rows] = measured < _SLOPE_MIN_VOTES
                blind &= ~jumps
            stats["refused_slope"], stats["refused_unmeasured"] = int(jumps.sum()), int(blind.sum())
            keep = ~(jumps | blind)
            accept_c, accept_k, accept_n = accept_c[keep], accept_k[keep], accept_n[keep]
            acc_rows, acc_height = acc_rows[keep], acc_height[keep]
    stats["refused_votes"] = (stats["components_tried"] - int(accept_c.size) - stats["refused_slope"]
                              - stats["refused_unmeasured"])
    # the markers at the linked offset must agree with the component's colours
    if accept_c.size:
        is_marker = pattern.is_marker()
        take = np.zeros(segs.n, np.bool_)
        take[accept_c] = True
        shift = np.zeros(segs.n, np.int64)
        shift[accept_c] = 2 * accept_k
        n_px, n_bad = kernels.component_marker_counts(comp, np.ascontiguousarray(un.relative, dtype=np.int32),
                                                      np.ascontiguousarray(labels, dtype=np.uint8), shift, take,
                                                      is_marker)
        fits = n_bad[accept_c] <= params.link_marker_frac * n_px[accept_c]
        stats["refused_markers"] = int((~fits).sum())
        accept_c, accept_k, accept_n = accept_c[fits], accept_k[fits], accept_n[fits]
        acc_rows, acc_height = acc_rows[fits], acc_height[fits]
    if accept_c.size and params.link_grad_tol > 0:
        # a component tied to the reported pixels only through its top or bottom rows (votes from
        # few rows, none along a row) hangs at a horizontal contact, where two surfaces' stripes
        # line up for an even shift and their slopes along the row may match as well (a tilted
        # panel before a wall, 8 stripes apart at 140-160 mm baselines).  Unless markers of its
        # own fix the offset, the column's gradient along the stripes must continue too
        hang = acc_height > params.link_hang_rows
        if params.link_slope_below_rows > 0:
            hang &= acc_rows < params.link_slope_below_rows
        if hang.any():
            # agreeing votes along a row (a side contact) at the component's offset
            off_of = np.full(segs.n, np.iinfo(np.int64).min, np.int64)
            off_of[accept_c] = accept_k
            side = good & (vl < 0)
            side[side] = off_of[vc[side]] == k[side]
            has_side = np.zeros(segs.n, bool)
            has_side[vc[side]] = True
            hang &= ~has_side[accept_c]
        refuse = np.zeros(accept_c.size, bool)
        if hang.any():
            refuse[hang] = _gradient_jumps(vc, k, vl, vv, good, comp, cr, col_abs, accept_c[hang], accept_k[hang],
                                           params)
        if refuse.any():
            # markers of its own fix the offset: such a component is linked whatever its gradient
            # (``shift`` and ``is_marker`` are the marker check's above: it ran on a superset of
            # these components, with the same offsets)
            slot = np.full(segs.n, -1, np.int64)
            slot[accept_c[refuse]] = np.arange(int(refuse.sum()))
            seen = kernels.component_markers_seen(comp, np.ascontiguousarray(un.relative, dtype=np.int32),
                                                  np.ascontiguousarray(labels, dtype=np.uint8), shift, slot,
                                                  int(refuse.sum()), is_marker, int(params.min_marker_px))
            refuse[refuse] = seen < params.min_markers
            stats["refused_gradient"] = int(refuse.sum())
            keep = ~refuse
            accept_c, accept_k, accept_n = accept_c[keep], accept_k[keep], accept_n[keep]
    if not accept_c.size:
        return empty
    # a linked kept region keeps its id; a linked small component gets a new one
    comp_region = np.full(segs.n, -1, np.int64)
    reg_of_root = np.full(segs.n, -1, np.int64)
    reg_of_root[root[has & ~seg_indexed]] = sreg[has & ~seg_indexed]
    old = reg_of_root[accept_c]
    n_new = int((old < 0).sum())
    comp_region[accept_c] = np.where(old >= 0, old, n_reg + np.cumsum(old < 0) - 1)
    n_tot = n_reg + n_new
    seg_region = sreg.astype(np.int32).copy()
    mv = (seg_comp >= 0) & (comp_region[np.maximum(seg_comp, 0)] >= 0)
    seg_region[mv] = comp_region[seg_comp[mv]]
    r_acc = comp_region[accept_c]
    offset = np.zeros(n_tot, np.int64)     # the regions' arrays extended by the new ones
    offset[:n_reg] = idx.offset
    indexed = np.zeros(n_tot, bool)
    indexed[:n_reg] = idx.indexed
    linked = np.zeros(n_tot, bool)
    votes = np.zeros(n_tot, np.int64)
    dissent = np.zeros(n_tot, np.int64)
    offset[r_acc], indexed[r_acc], linked[r_acc] = 2 * accept_k, True, True
    votes[r_acc], dissent[r_acc] = accept_n, n_all[accept_c] - accept_n
    stats["components_linked"] = int(accept_c.size)
    stats["pixels_linked"] = int((segs.u1[mv] - segs.u0[mv] + 1).sum())
    return Links(seg_region, offset, indexed, linked, votes, dissent, stats)


_GRAD_MIN_VOTES = 5  # measured votes a component needs before its gradient along the stripes can refuse it
_GRAD_NOISE_FLOOR = 0.005  # smallest spread (px per row, MAD) assumed of one vote's gradient difference


def _gradient_jumps(vc, vk, vl, vv, good, comp, col_rel, col_abs, comps, offsets, params) -> np.ndarray:
    """(len(comps),) bool: the column's gradient along the stripes (``d column / d v``) jumps
    where the component meets the reported pixels it is linked to.

    The agreeing vertical votes of each component at its offset (``vc, vk, vl, vv, good`` of
    :func:`link_components`) are measured as :func:`gbscan.kernels.stripe_gradient_jumps` does
    (``link_grad_rows`` rows each side; one compiled pass, :func:`gbscan.kernels.
    gradient_jump_verdicts`).  With at least ``_GRAD_MIN_VOTES`` measured votes, a component is
    flagged when their median difference exceeds ``link_grad_tol`` px per row in size and
    ``link_grad_z`` standard errors (``1.4826 * MAD / sqrt(n)``, the MAD at least
    ``_GRAD_NOISE_FLOOR``), unless its contacts above and below, taken apart, have medians of
    opposite signs each at that z-score (the gradient changing steadily through it: one curved
    surface, as found on the real face).  A component tied through one contact alone (its
    agreeing votes all on one side) is flagged at ``link_grad_z_one`` standard errors instead.
    """
    from . import kernels

    comps = np.asarray(comps, dtype=np.int64)
    if comps.size == 0:
        return np.zeros(0, bool)
    slot = np.full(max(int(comps.max()), int(vc.max())) + 1, -1, np.int64)
    slot[comps] = np.arange(comps.size)
    return kernels.gradient_jump_verdicts(
        np.ascontiguousarray(vc, dtype=np.int64), np.ascontiguousarray(vk, dtype=np.int64),
        np.ascontiguousarray(vl, dtype=np.int64), np.ascontiguousarray(vv, dtype=np.int64),
        np.ascontiguousarray(good, dtype=np.bool_), np.ascontiguousarray(comp, dtype=np.int32),
        np.ascontiguousarray(col_rel, dtype=np.float32), np.ascontiguousarray(col_abs, dtype=np.float32), slot,
        np.asarray(offsets, dtype=np.int64), int(params.link_grad_rows), float(params.link_grad_tol),
        float(params.link_grad_z), _GRAD_MIN_VOTES, _GRAD_NOISE_FLOOR, int(params.link_grad_skip_rows),
        float(params.link_grad_z_one))


_SLOPE_MIN_VOTES = 5  # measurable votes a component needs before its slope can refuse it
_SLOPE_NOISE_FLOOR = 0.005  # smallest spread (log slope ratio) assumed of one vote's measurement


def _slope_jumps(vc, vk, vl, vv, comp, col_rel, col_abs, region, comps, offsets, rows: int, half_px: int,
                 tol: float, z_min: float, return_measured: bool = False, z_near: float | None = None):
    """(len(comps),) bool: across the component's agreeing vertical votes the column's slope
    along the row (projector px per camera px) differs between the component and the reported
    pixels it is linked to.

    ``vc, vk, vl, vv``: agreeing votes of :func:`link_components` (component, offset in periods of
    two stripes, line, candidate row; vertical votes have ``line`` = column >= 0); ``comp`` (H, W)
    int32 component of the candidate pixels, ``col_rel`` their relative column, ``col_abs`` the
    reported absolute column, ``region`` (H, W) int32 the regions of the reported pixels.  For
    each vote at (v, u) whose reported pair lies on side ``d`` (above, else below), slopes are
    taken along a row between the outermost pixels within +-``half_px`` px
    (as :func:`gbscan.kernels.window_slopes`, spanning at least ``half_px`` px) in the component,
    ``rows`` to ``2*rows - 1`` rows into it (the first measurable row: away from the contact,
    where the along-stripe blur mixes the two surfaces), and in the voting pixel's region,
    likewise from ``rows`` rows (*near*) and from ``3*rows`` rows (*deep*: past a strip of the
    component's surface welded into that region) into it.  With at least ``_SLOPE_MIN_VOTES``
    measured votes, the median ``m`` of ``log(slope_component / slope_region)`` must not exceed
    ``log(1 + tol)`` (near, all votes) or ``log(1 + 2 tol)`` (deep, the votes from above and below
    apart) in size while exceeding ``z_min`` standard errors (``1.4826 * MAD / sqrt(n)``, the MAD
    at least ``_SLOPE_NOISE_FLOOR``: a consistent jump, not the scatter of a noisy frame);
    otherwise the component is flagged.  Without measured votes it never is.  ``return_measured``:
    also return the number of measured *near* votes per component ((len(comps),) int64), for
    :func:`link_components`' rule that a component the test cannot measure is not linked.
    ``z_near``: the near test's z threshold when it differs from ``z_min`` (the deep one's).
    """
    from . import kernels

    comps = np.asarray(comps, dtype=np.int64)
    if comps.size == 0:
        return np.zeros(0, bool)
    # one compiled pass over the votes of these components only (kernels.slope_samples; the other
    # votes cannot change a verdict), the log ratios in numpy, the medians compiled
    # (kernels.slope_verdicts).  tests/test_unwrap.py keeps the numpy form this replaced (same
    # verdicts; 5 ms -> 0.2 ms on a hard-preset frame with ~10^4 votes)
    c, kk, d, g_c, g_n, g_d = kernels.slope_samples(
        np.ascontiguousarray(vc, dtype=np.int64), np.ascontiguousarray(vk, dtype=np.int64),
        np.ascontiguousarray(vl, dtype=np.int64), np.ascontiguousarray(vv, dtype=np.int64),
        np.ascontiguousarray(comp, dtype=np.int32), np.ascontiguousarray(col_rel, dtype=np.float32),
        np.ascontiguousarray(col_abs, dtype=np.float32), np.ascontiguousarray(region, dtype=np.int32), comps,
        np.asarray(offsets, dtype=np.int64), int(rows), int(half_px))
    lrs = []
    for g_s in (g_n, g_d):
        fin = np.isfinite(g_c) & np.isfinite(g_s) & (g_c > 0) & (g_s > 0)
        lr = np.full(c.size, np.nan)
        lr[fin] = np.log(g_c[fin] / g_s[fin])
        lrs.append(lr)
    offs64 = np.asarray(offsets, dtype=np.int64)
    if z_near is None or float(z_near) == float(z_min):
        out = kernels.slope_verdicts(c, kk, d, lrs[0], lrs[1], comps, offs64, float(np.log1p(tol)),
                                     float(np.log1p(2 * tol)), float(z_min), _SLOPE_MIN_VOTES, _SLOPE_NOISE_FLOOR)
    else:  # the near and the deep test at their own z (a NaN ratio is not measured)
        none = np.full(c.size, np.nan)
        out = kernels.slope_verdicts(c, kk, d, lrs[0], none, comps, offs64, float(np.log1p(tol)),
                                     float(np.log1p(2 * tol)), float(z_near), _SLOPE_MIN_VOTES, _SLOPE_NOISE_FLOOR)
        out |= kernels.slope_verdicts(c, kk, d, none, lrs[1], comps, offs64, float(np.log1p(tol)),
                                      float(np.log1p(2 * tol)), float(z_min), _SLOPE_MIN_VOTES, _SLOPE_NOISE_FLOOR)
    if not return_measured:
        return out
    # measured near votes per (component, offset): few comps, a mask each
    offs = np.asarray(offsets, dtype=np.int64)
    fin = np.isfinite(lrs[0])
    measured = np.array([int(((c == cc) & (kk == oo) & fin).sum()) for cc, oo in zip(comps, offs)], np.int64)
    return out, measured
