"""Multi-body 3D-2D registration: settings, pyramid, stage 1, stage 2, re-search, orchestrator.

The entry points are :func:`~pelvicnav.register.multibody.register_multibody` (a CT and label
map) and :func:`~pelvicnav.register.multibody.register` (any renderer).
"""
