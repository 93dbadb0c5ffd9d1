"""flowmod: flow-based moving-object detection (a re-implementation of Lo, "Optical Flow Based
Motion Detection for Autonomous Driving").

One module per pipeline stage: ``world`` (synthetic nuScenes-format data), ``select``,
``labels``, ``flow``, ``crops``, ``model``, ``train``, ``evaluate``; shared: ``params``,
``paths``, ``artefacts``, ``runner`` (papermill driver), ``book`` (Sphinx assembly).
"""

__version__ = "0.1.0"
