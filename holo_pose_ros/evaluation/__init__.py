"""Evaluation of pose estimates against ground truth, as HoRoPose, RoboPose and DREAM report it: per-frame metrics
(metrics), the JSON report over a data set (report) and figures (plots). Pure numpy and matplotlib."""
