"""Exceptions a user can cause, one type per kind.

Every message names the file / key / value at fault and how to fix it; the CLI prints the
message without a traceback.
"""


class MsDrakeError(Exception):
    """Base class of every error ms_drake raises on bad user input."""


class ScenarioError(MsDrakeError, ValueError):
    """A scenario file or scenario value is malformed (unknown key, wrong type, bad value)."""


class ObjectSetError(MsDrakeError, KeyError):
    """An unknown object set or object name, a missing mesh, or an impossible object count."""

    def __str__(self):  # KeyError would repr() the message; keep it readable.
        return str(self.args[0]) if self.args else ""


class HeapError(MsDrakeError, RuntimeError):
    """A heap could not be generated (e.g. more objects than fit, every resample invalid)."""


class ModelNotFoundError(MsDrakeError, FileNotFoundError):
    """A model file (mesh, SDF, URDF, weights) is missing."""


class PerceptionError(MsDrakeError, ValueError):
    """A perception system was configured or fed with impossible values (names what and how to fix)."""


class SceneError(MsDrakeError, RuntimeError):
    """A shelf scene could not be generated (impossible request, no hiding place after the bounded tries)."""


class DatasetError(MsDrakeError, ValueError):
    """A dataset folder, shard or training request that cannot be used (names the file and the
    command that makes it)."""


class RecordFileError(MsDrakeError, ValueError):
    """A result (JSON-lines record) file that cannot be read: missing, empty, a line that is not a
    record, or records without the fields the reader needs (names the file, the line and the
    command that writes it)."""


class DeviceError(MsDrakeError, ValueError):
    """A torch device that is unknown or absent on this machine (names the value and the choices)."""
