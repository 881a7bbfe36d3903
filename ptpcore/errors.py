"""Exceptions the engine raises on bad input.

Every error a user can cause derives from :class:`PtpError`; the CLI and the
GUI show its message as one line. The message always names the culprit (a
file, a TOML key, a value).
"""


class PtpError(Exception):
    """Base class of user-facing errors (bad input, bad files)."""


class ConfigError(PtpError, ValueError):
    """A configuration document (``rig.toml``) is invalid."""


class DatasetError(PtpError):
    """A dataset folder or one of its images is missing or unusable."""


class FileFormatError(PtpError):
    """A LUT, session or report file is not what its format promises."""


class Cancelled(PtpError):
    """Raised by a progress callback to stop a long job."""


class DeviceError(PtpError):
    """A camera, stage or display failed, timed out or cannot be reached.

    The message names the device and what it was asked to do; a capture that
    stops on one is left resumable (``ptpcore.capture``).
    """


class CaptureError(PtpError):
    """A live capture cannot start or go on (folder, plan or exposure problem)."""


class OutputError(PtpError):
    """An output path cannot or must not be written (checked before the work starts).

    The message names the path and the reason (missing or read-only folder, a
    file of the input dataset, an existing file of another kind, an existing
    result replaced without ``--force``).
    """


class DataWarning(UserWarning):
    """The data look wrong though they can be processed (a stuck stage, MSB-aligned samples).

    The message names the positions or the file and what to check.
    """
