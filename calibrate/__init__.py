"""Camera-only calibration: a DEFORM model of a new rope from bags of a robot moving it in front of
an RGB-D camera (``deform calibrate``; issue 49).

The pipeline, one module each:

- :mod:`calibrate.bags`: rosbag2 folders and MCAP files -> :class:`Clip` (gripper poses, clouds,
  camera), topics found by message type;
- :mod:`calibrate.tracks`: a clip tracked offline by perception's :class:`perception.Tracker`
  -> :class:`Track` (a recording-like (T, n, 3) track, which vertices the camera saw);
- :mod:`calibrate.checks`: what the tracks say about the input (rope seen, its length, enough motion);
- :mod:`calibrate.fit`: identification and residual training on the tracks, tracking again with the
  better model while the fit on held-out clips improves;
- :mod:`calibrate.damping`: the damping set on the training clips' 3 s predictions after each
  round's training (the 1 s training windows barely see it);
- :mod:`calibrate.report`: ``report.md``, ``report.json`` and plots.

Layer: above :mod:`service` (its message codecs and gripper convention), so the model layer runs
it as a program (``python -m calibrate``), never as an import.
"""

from calibrate.bags import Clip, Topics, read_clip
from calibrate.errors import CalibrationError
from calibrate.fit import Budget, Calibration, calibrate
from calibrate.tracks import Track, track_clip

__all__ = [
    "Budget",
    "Calibration",
    "CalibrationError",
    "Clip",
    "Topics",
    "Track",
    "calibrate",
    "read_clip",
    "track_clip",
]
