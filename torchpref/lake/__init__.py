"""The simulated lake-monitoring world of the paper (Sec. IV.B): an information field over a
lake, two planners that trade distance for information, path objectives and the operator."""

from .field import InformationField, bilinear_sample, perlin_grid, perlin_noise
from .geometry import Lake
from .objectives import path_information, path_length, path_objectives
from .operator import LakeOperator
from .planners import path_cost, rrt_star, stomp
from .scenario import PLANNERS, LakeScenario, make_scenario

__all__ = [
    "InformationField",
    "Lake",
    "LakeOperator",
    "LakeScenario",
    "PLANNERS",
    "bilinear_sample",
    "make_scenario",
    "path_cost",
    "path_information",
    "path_length",
    "path_objectives",
    "perlin_grid",
    "perlin_noise",
    "rrt_star",
    "stomp",
]
