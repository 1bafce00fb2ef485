"""Grasping: contact-model grasp quality (point, soft point, elliptical, REACH, MFE, 6DFC),
the wrench QP on Drake's MathematicalProgram, robust quality, samplers, suction, the
GraspPlanner system and physics labels (the contact models and their outcomes: evaluator.py)."""

from ms_drake.grasping.evaluator import (  # noqa: F401
    AREA_MODELS,
    MODELS,
    GraspEvaluator,
    GraspQuality,
    PadGeometry,
)
from ms_drake.grasping.grasp import GraspError, ParallelJawGrasp, SuctionGrasp  # noqa: F401
