"""Rerun recordings of warpmpm runs: written by :class:`viewer.recording.RerunRecorder` (a
:class:`warpmpm.recorder.Recorder`), opened with ``python -m viewer RUN.rrd`` (or ``warpmpm view``),
summarised headless with ``--summary``. The viewer only reads the library; the library never imports it."""
