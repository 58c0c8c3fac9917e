"""The simulated rig: scenes, image formation, imaging presets, ground truth.

```python
from gbscan import sim
rig = sim.paper_rig()
cond = sim.preset("typical")                   # "clean" | "typical" | "hard" -> sim.Conditions
scene = sim.scenes.plane(distance_mm=650, tilt_deg=(0, 20))
r = sim.render(rig, scene, projector_rgb, cond, seed=0)   # -> sim.Render
```
One view under many projector frames: ``tr = sim.trace(rig, scene, cond)`` once, then
``sim.render_traced(rig, tr, frame, seed)`` per frame (only projector sampling and camera noise
run again).  An object moving during the exposure: ``sim.render_moving(rig, poses, frame, cond)``
with poses from ``sim.scenes.moved(scene, R, t_mm)``.  See :mod:`gbscan.sim.render` for the
image formation and :mod:`gbscan.sim.presets` for the conditions.  Everything is in the OpenCV
camera frame, mm.
"""
from __future__ import annotations

from ..rig import paper_rig
from . import scenes
from .presets import PRESETS, Conditions, preset
from .render import (Render, Trace, camera_image, column_errors, decode_dn, encode, incidence_deg, linear_signal,
                     lateral_ca, point_errors_mm, render, render_moving, render_traced, trace,
                     yuv_round_trip)
from .scenes import Scene, combine

__all__ = ["paper_rig", "scenes", "Conditions", "PRESETS", "preset", "Render", "render", "render_moving", "Scene",
           "combine",
           "encode", "decode_dn", "Trace", "trace", "render_traced", "linear_signal", "camera_image",
           "incidence_deg", "point_errors_mm", "column_errors", "yuv_round_trip", "lateral_ca"]
