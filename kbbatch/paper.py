"""The method's constants, each named once (Niklaus et al. 2019 and its documented reference facts).

Every stage imports from here, so a number from the paper never appears bare elsewhere.
"""

# --- Geometry (section 3.3) -------------------------------------------------------------
WORKING_LONG_SIDE_PX = 1024
"""Depth, camera and planning all happen on the image resized to this long side."""

FOCAL_PER_LONG_SIDE = 0.5
"""Focal length as a fraction of the working long side: f = 512 px at 1024 px."""

DISPARITY_MAX_PX = 40.0
"""Disparity is normalised so that its maximum is this (baseline b = 40): nearest depth = f."""

DISPARITY_FLOOR_FRACTION = 0.02
"""Smallest disparity kept, as a fraction of the maximum: the sky sits 50x farther than the
nearest surface instead of at infinity (our choice; the paper does not say)."""

ZMIN_BORDER_PX = 128
"""The nearest depth, which anchors the dolly, ignores this border at the working size."""

# --- Automatic mode (section 3.4) -------------------------------------------------------
START_CROP_FRACTION = 0.97
"""The automatic start view is the whole image less a 3 % margin."""

AUTO_SEARCH_GRID = 16
"""The end crop's centre is searched on this many positions per axis, over +- the preset's
max_shift_px. The paper's zoom (1.25), search range (100 px) and reference clip (75 linear
steps at 25 fps) are preset settings: see presets/reference.toml."""


# --- Point cloud rendering (section 3.2) ------------------------------------------------
DEPTH_EDGE_LAPLACIAN = 0.03
"""Points whose |Laplacian of normalised disparity| reaches this sit on a depth edge and are
removed, so that no rubber sheet stretches across a discontinuity."""

EXTREME_VIEW_OVERSHOOT = 1.1
"""The end view is inpainted with its 3D move overshot by this factor, so that every frame in
between stays inside what was filled."""

# --- Semantic adjustment (section 3.1) --------------------------------------------------
SALIENT_SCORE_MIN = 0.7
SALIENT_MASK_MIN_PX = 64
ACCESSORY_OVERLAP_MIN = 0.03
"""An accessory joins an object when it overlaps it by this fraction of its own area."""
GROUND_CONTACT_FRACTION = 0.03
"""An object's single disparity is the largest found in this bottom fraction of its box."""
SALIENT_CLASSES = (
    "person", "car", "bus", "train", "truck", "boat", "bird", "cat", "dog", "horse", "sheep",
    "cow", "elephant", "bear", "zebra", "giraffe",
)
ACCESSORY_CLASSES = (
    "bicycle", "motorcycle", "backpack", "umbrella", "handbag", "tie", "suitcase",
)


def focal_px(long_side_px: float) -> float:
    """Focal length in pixels for an image of this long side."""
    return FOCAL_PER_LONG_SIDE * long_side_px
