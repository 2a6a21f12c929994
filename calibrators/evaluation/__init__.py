"""Evaluation: detections matched to ground truth, and what is measured on them.

- `_matching`: the nuScenes devkit's greedy centre-distance matching, `match`.
- `_dump_match`: a dump matched (`match_dump`), its true positives' residuals
  (`tp_residuals`) and the temperature-scaling targets (`ts_labels`, `ts_logits`).
- `_ap`, `_nuscenes_metrics`: nuScenes mAP, TP errors and NDS, `evaluate`.
- `_summary`, `_reports`: the before / after calibration report of a profile on a dump
  (`summarize` -> `Summary`, `ProfileReport`) and its text table (`format_table`).
"""

from calibrators.evaluation._ap import calc_ap, calc_tp
from calibrators.evaluation._dump_match import match_dump, tp_residuals, ts_labels, ts_logits
from calibrators.evaluation._matching import DEFAULT_CLASS_RANGE, MatchResult, in_range, match
from calibrators.evaluation._nuscenes_metrics import TP_METRICS, EvaluationReport, evaluate
from calibrators.evaluation._reports import (
    ClassSummary,
    Counts,
    CoverageSummary,
    Pair,
    ProfileReport,
    RegressionSummary,
    Summary,
)
from calibrators.evaluation._summary import SUMMARY_LEVELS, format_table, summarize

__all__ = ["DEFAULT_CLASS_RANGE", "SUMMARY_LEVELS", "TP_METRICS", "ClassSummary", "Counts",
           "CoverageSummary", "EvaluationReport", "MatchResult", "Pair", "ProfileReport",
           "RegressionSummary", "Summary", "calc_ap", "calc_tp", "evaluate", "format_table",
           "in_range", "match", "match_dump", "summarize", "tp_residuals", "ts_labels",
           "ts_logits"]
