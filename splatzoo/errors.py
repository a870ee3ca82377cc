"""Exceptions raised by splatzoo. Each message says what was wrong and what to do."""


class SplatzooError(Exception):
    """Base class for every error splatzoo raises on purpose."""


class UnknownNameError(SplatzooError, KeyError):
    """A model, backend or scene name that is not registered."""

    def __str__(self) -> str:  # KeyError would otherwise quote the message
        return str(self.args[0]) if self.args else ""


class DuplicateNameError(SplatzooError):
    """Two registrations under one name."""


class ShapeError(SplatzooError, ValueError):
    """A tensor with the wrong shape, dtype or non-finite values."""


class DataError(SplatzooError):
    """A dataset that cannot be read: missing files, corrupt images, unsupported cameras."""


class BackendUnavailableError(SplatzooError, RuntimeError):
    """A rasterizer backend that cannot be built or run here."""


class PluginError(SplatzooError):
    """A third-party model plugin that failed to load."""
