"""Whether a run learns a tone per photo when nobody said (`tonemap.enabled` None, the default): on when
the photos' camera settings vary, off when one fixed camera took them all, as measured from the photos
(`data.camera_spread`).

Plain Plenoxels is the right model for photos of one fixed camera, and the tone mapper can cost there (the
room scene's static captures at `fast`: 1.55 dB on validation views); where the settings vary it is what
makes the model work at all. The thresholds sit between what fixed cameras and varying ones measured
(JOURNAL.md, "Tone mapping on or off"): synthetic fixed cameras spread their views' pixels by at
most 0.07 stops of exposure and 0.03 of white balance and kermit's fixed camera by 0.10 and 0.03, while
brackets spread them by 1.0-2.0 and 0.11-0.13, and real auto-exposure captures by 0.29-0.38 and
0.05-0.17. EXIF that shows the exposure changing decides alone.
"""

from __future__ import annotations

from hdrplenoxels.data.camera_spread import CameraSpread, camera_spread
from hdrplenoxels.data.scene import SceneData

EXIF_STOPS = 1 / 3  # EXIF exposures spread by more than a third of a stop: the camera varied
EXPOSURE_STOPS = 0.2  # views' pixels disagree by more than this in exposure (stops of 8-bit code)
WHITE_BALANCE_STOPS = 0.06  # ... or by more than this in one channel's balance


def choose_tone_mapping(scene: SceneData, views: list[int]) -> tuple[bool, str, CameraSpread]:
    """(on, why in words, what was measured) for a run training on `views` of `scene`."""
    spread = camera_spread(scene, views, pixels=False)
    if spread.exif_stops is not None and spread.exif_stops > EXIF_STOPS:
        return True, f"the photos' EXIF exposures span {spread.exif_stops:.2f} stops", spread
    spread = camera_spread(scene, views)
    if spread.exposure_stops is None:
        return True, "too few views overlap to tell whether the camera's settings varied", spread
    measured = (
        f"overlapping views differ by {spread.exposure_stops:.2f} stops in exposure and "
        f"{spread.white_balance_stops:.2f} in white balance"
    )
    if spread.exposure_stops > EXPOSURE_STOPS or spread.white_balance_stops > WHITE_BALANCE_STOPS:
        return True, f"the camera's settings varied: {measured}", spread
    return False, f"one fixed camera: {measured}", spread
