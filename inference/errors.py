"""Runtime errors with the field that was wrong; the service maps them to problem+json 4xx."""
from __future__ import annotations


class InferenceInputError(ValueError):
    """Bad input to a pipeline stage. ``field`` names what was wrong (a request path when known)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.detail = message


class InputShapeError(InferenceInputError):
    """An array has the wrong shape: expected vs actual."""

    def __init__(self, field: str, expected: str, actual):
        super().__init__(field, f"expected shape {expected}, got {tuple(actual)}")


class InputValueError(InferenceInputError):
    """A value is out of its documented range or not finite."""


class UnknownAssetError(InferenceInputError):
    """A garment id or motion clip id that the catalog does not have."""
