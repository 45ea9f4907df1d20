"""Data for analysis: a recorded run as pandas tables (:func:`load`) and as Parquet or CSV files
(``flocktrack export``). Needs the ``analysis`` extra (pandas, pyarrow); importing this package does not
import pandas."""

from flocktrack.analysis.loader import LoadError, Run, TruncatedRecordingWarning, load

__all__ = ["LoadError", "Run", "TruncatedRecordingWarning", "load"]
