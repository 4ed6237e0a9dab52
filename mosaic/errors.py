"""Errors a user can act on: the CLI prints the message on one line and exits with code 2."""


class MosaicError(Exception):
    """Base of every error whose message is meant for the user."""


class InputError(MosaicError):
    """The input (path, video, frame folder, image) cannot be used."""


class ConfigError(MosaicError):
    """The configuration file or a value in it is invalid."""


class OutputError(MosaicError):
    """An output cannot be written (missing or read-only folder)."""


class DetectorWeightsError(MosaicError):
    """The detector's weights cannot be loaded (missing file, not a weights file, another
    network): glampoints' `WeightsError` as the features adapter raises it."""


class CanvasLimitError(MosaicError):
    """Placing a frame would grow the mosaic canvas beyond its configured cap."""
