"""pelvicnav: image-guided reduction of pelvic dislocation.

Preoperative planning from CT with a statistical pose model, and intraoperative multi-body 3D-2D
registration of the sacrum and both innominate bones to fluoroscopy (Han et al., Phys. Med. Biol.
2020, doi:10.1088/1361-6560/ab843c).
"""

__version__ = "0.1.0"

BONES: tuple[str, str, str] = ("sacrum", "left_hip", "right_hip")
"""Bone order used everywhere (arrays, label values 1, 2, 3)."""

LABELS: dict[str, int] = {"sacrum": 1, "left_hip": 2, "right_hip": 3}
"""Label-map values of each bone."""
