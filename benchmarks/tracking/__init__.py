"""Tracking side by side with the published trackers (issue 50): the scenarios, the metric, the runner
and the tables and plots of ``benchmarks/tracking_peers.py``.

- :mod:`.metric`: the field's error (TrackDLO's mean two-way distance to the true polyline), the
  recovery time after a blackout, arc-length resampling.
- :mod:`.contact`: ground truth with contact the tracker's model does not know (a table, a post),
  simulated with this project's model plus contact forces that live here only.
- :mod:`.scenarios`: which recordings, which clouds, which model: the cases of each scenario.
- :mod:`.runner`: every method on the same rendered clouds; errors and update times.
- :mod:`.report`: the summary JSON, the markdown table and the error-over-time plots.
"""
