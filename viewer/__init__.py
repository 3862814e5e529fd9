"""Rerun recordings of warpmpm runs: write with :class:`viewer.recording.RunLogger`, open with
``python -m viewer RUN.rrd`` or summarise headless with ``python -m viewer --summary RUN.rrd``."""
