"""The package's exception hierarchy: one base class, one subclass per failure kind.

Every layer raises these; the CLI maps them to one clear line and a non-zero exit code.
"""


class SwarmsplatError(Exception):
    """Base class of every error swarmsplat raises on purpose."""

    exit_code = 1


class InputError(SwarmsplatError, ValueError):
    """Bad user input: a file, field, argument or array that is not what was expected.

    The message names the file (with line number where there is one) or the argument, and what was expected.
    """

    exit_code = 2


class OutputError(SwarmsplatError, OSError):
    """A file the run could not write once it had started: the disk is full, or the place refused the write.

    The message names the file and, for a full disk, says so. What was written before stays whole (atomic writes,
    the fsync'd pose journal), so a run's folder keeps its last checkpoint. `full`: the disk (or quota) is full.
    """

    exit_code = 1

    def __init__(self, message: str, *, full: bool = False, errno: int | None = None):
        super().__init__(message)
        self.full, self.errno = full, errno


class BackendError(SwarmsplatError, RuntimeError):
    """A kernel backend or device that cannot be used here (no CUDA, unknown backend, not initialised)."""

    exit_code = 3


class RegistrationError(SwarmsplatError, RuntimeError):
    """A registration that cannot even be attempted (as opposed to one that ran and failed its gates)."""


class GraphError(SwarmsplatError, RuntimeError):
    """A pose graph that cannot be built or solved."""


class DeviceCheckError(BackendError):
    """A backend/device that loads but fails its self-check: a driver error, or a probe render that differs from
    the twin (kernels.selfcheck)."""


class SanityError(SwarmsplatError, RuntimeError):
    """A pipeline result that cannot be right: a new submap left empty where the keyframe has valid depth, a render
    with no alpha where depth is valid, parameters that are not finite."""
