"""Trajectory evaluation (ATE, RPE) with evo."""

from surfelslam.eval.metrics import AteResult, RpeResult, associate, ate, evaluate, evaluate_all, rpe, summary

__all__ = ["AteResult", "RpeResult", "associate", "ate", "evaluate", "evaluate_all", "rpe", "summary"]
