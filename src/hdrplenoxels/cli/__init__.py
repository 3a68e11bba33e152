"""The `hdrplenoxels` command. Its entry point applies the process-wide settings before torch loads."""

from hdrplenoxels.core.process_settings import apply_process_settings

apply_process_settings()

from hdrplenoxels.cli.main import main  # noqa: E402  (after the settings: this imports torch)

__all__ = ["main"]
