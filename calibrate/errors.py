"""The one error calibration reports to the user: bad input, named in a single line."""

from __future__ import annotations


class CalibrationError(ValueError):
    """Input calibration cannot use (a bag without poses or clouds, a colour range that finds no
    rope, a length the camera contradicts); the message is one line naming the file and the problem,
    which ``deform calibrate`` prints before exiting with code 2 without writing anything."""
