"""The one exception class of the data sources."""

__all__ = ["DatasetError"]


class DatasetError(ValueError):
    """A sequence, list or trajectory file that cannot be read; the message names the file."""
