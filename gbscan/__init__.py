"""gbscan: single-shot green-blue stripe range sensing -- decode, triangulate, clean, mesh.

Module map (by concept):

* ``camera``, ``rig``, ``pattern``: geometry and the projected pattern (conventions live there).
* ``io``, ``calibfile``: files at the edge (images, sessions, the calibration file).
* ``sim``: the simulated rig (scenes, image formation, ground truth, sessions).
* ``decode``, ``unwrap``: colour-stripe segmentation and unwrapping (the paper) + absolute index.
* ``triangulate``, ``clean``, ``mesh``, ``preview``: range, cleaning, meshing, pictures.
* ``cli``: the ``gbscan`` command.
"""

__version__ = "0.1.0"
