"""Exception hierarchy of softgrasp.

Every error softgrasp raises on purpose derives from :class:`SoftgraspError`; the command-line
interface turns any of them into one clear line and a non-zero exit status.
"""

from __future__ import annotations

__all__ = [
    "SoftgraspError",
    "MeshError",
    "MaterialError",
    "ContactError",
    "InfeasibleGrasp",
    "NotConverged",
    "SimulationUnstable",
    "ConfigError",
    "SoftgraspWarning",
    "diagnosis",
]


class SoftgraspError(Exception):
    """Root of every error raised deliberately by softgrasp."""


class MeshError(SoftgraspError):
    """A mesh is unusable: bad shape, inverted or degenerate tets, broken boundary, bad file."""


class MaterialError(SoftgraspError):
    """A material parameter or stress-strain law is outside its valid range."""


class ContactError(SoftgraspError):
    """A contact parameter or fingertip description is invalid."""


class InfeasibleGrasp(SoftgraspError):
    """No grasp satisfying the requested conditions exists (unreachable, no equilibrium, ...)."""


class NotConverged(SoftgraspError):
    """An iterative solver stopped before reaching its tolerance.

    Attributes
    ----------
    diagnosis: what the solver did (the message without ``advice``).
    advice: what a user may change to help it, or None; the message ends with it.
    """

    def __init__(self, diagnosis: str, advice: str | None = None) -> None:
        super().__init__(diagnosis if advice is None else f"{diagnosis}; {advice}")
        self.diagnosis = diagnosis
        self.advice = advice


def diagnosis(exc: BaseException) -> str:
    """What a failed solver did, without the advice its message may end with
    (:attr:`NotConverged.diagnosis`; any other exception's whole message): for a message that
    embeds it and gives its own advice."""
    return exc.diagnosis if isinstance(exc, NotConverged) else str(exc)


class SimulationUnstable(SoftgraspError):
    """A time integration blew up (NaN, energy growth, inverted tets).

    Attributes
    ----------
    suggested_dt:
        A time step [s] that should be stable, or ``None`` when no suggestion can be made.
    """

    def __init__(self, message: str, suggested_dt: float | None = None) -> None:
        super().__init__(message)
        self.suggested_dt = suggested_dt


class ConfigError(SoftgraspError):
    """A command-line option or configuration value is invalid."""


class SoftgraspWarning(UserWarning):
    """A default softgrasp took where the user gave nothing (a mesh file's material or density):
    the command line prints it as one line on stderr."""
