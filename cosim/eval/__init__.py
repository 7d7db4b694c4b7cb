"""Evaluation on cosim data (docs/evaluation.md): detection AP and BEV segmentation IoU per condition and
collaboration setting (``cosim eval``), ground-truth collaborative coverage (``cosim coverage``), and
reference baselines that need no training."""
