"""The suite runs with the command line's process settings, as a library user applying them would."""

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()
