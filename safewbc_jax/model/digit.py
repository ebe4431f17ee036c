"""Digit's names and numbers: the frames, bodies and motors of the models (``models/``) that
the controller, the scenarios and the simulators refer to, and the height below which the
robot has fallen."""

SIDES = ("left", "right")
BASE = "base"                       # the floating base: its body and free joint
TORSO = "torso"                     # the frame the arm task's fist heights are in (eq. 33)
LEFT_SOLE, RIGHT_SOLE = "left-sole", "right-sole"   # a site (and a collision box) per sole
SOLES = (LEFT_SOLE, RIGHT_SOLE)
FALL_HEIGHT = 0.55                  # m: the base below this counts as a fall


def sole(side: str) -> str:
    """The sole site of ``side`` ("left" or "right")."""
    return f"{side}-sole"


def fist(side: str) -> str:
    """The fist site of ``side``."""
    return f"{side}-fist"


def toe_motors(side: str) -> tuple[str, str]:
    """The two motors of ``side``'s toe (A and B, through the toe rods)."""
    return f"{side}-toe-A", f"{side}-toe-B"
