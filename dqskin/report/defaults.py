"""The report's defaults and limits, in a module that imports nothing (the command line's parser
reads them without loading Warp, NumPy or the report's modules)."""

__all__ = ["MAX_RAYS", "VIEWER_FRAMES", "VIEWS"]

VIEWS = ("front", "side", "three_quarter")
"""Named view directions of :meth:`dqskin.report.render.Camera.frame`."""

MAX_RAYS = 8192
"""Default limit on rays per image side (``width × supersample``; ``--max-rays`` raises it): an
8192² super-sampled image is already 768 MB of colour samples."""

VIEWER_FRAMES = 48
"""Default number of frames the viewer plays (evenly spaced over the clip; plus the compared
frames, so the worst frames are exact)."""
