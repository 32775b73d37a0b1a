"""Errors raised by identification: each message names what is wrong with the input."""
from __future__ import annotations


class IdentificationError(ValueError):
    """The data or the request cannot give an estimate (bad samples, too short, no excitation...)."""


class NotIdentifiableError(IdentificationError):
    """The experiment cannot separate the requested parameters (rank-deficient Jacobian).

    ``parameters`` lists the parameters involved in the unidentifiable direction(s).
    """

    def __init__(self, message: str, parameters: list[str]):
        super().__init__(message)
        self.parameters = list(parameters)
