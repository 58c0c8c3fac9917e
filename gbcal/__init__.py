"""gbcal: calibration of a green-blue stripe rig -- camera intrinsics, light planes, bundle.

Module map: ``board`` (checkerboard model and detection), ``intrinsics`` (camera alone),
``planes`` (stripe planes from board captures), ``bundle`` (joint refinement), ``report``
(pictures and summaries), ``diff`` (comparing calibrations), ``cli`` (the ``gbcal`` command).
"""

__version__ = "0.1.0"
