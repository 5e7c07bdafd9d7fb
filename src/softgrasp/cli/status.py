"""The exit statuses of ``softgrasp``: what each means and which errors give which.

=====  ==========================================================================================
0      done
1      the computation ended without the result asked for, on valid input: no grasp holds the
       object (:class:`~softgrasp.errors.InfeasibleGrasp`), ``execute`` dropped it, a ``sweep``
       case failed, or a solver found no equilibrium or blew up
       (:class:`~softgrasp.errors.NotConverged`, :class:`~softgrasp.errors.SimulationUnstable`)
2      bad input: an option, file, mesh, material, contact parameter or output folder refused
       (:class:`~softgrasp.errors.ConfigError`, :class:`~softgrasp.errors.MeshError`,
       :class:`~softgrasp.errors.MaterialError`, :class:`~softgrasp.errors.ContactError`, the
       argument parser), or an optional extra the command needs is not installed
3      internal error: a bug in softgrasp (its traceback with ``--debug``)
130    interrupted (Ctrl-C)
=====  ==========================================================================================
"""

from __future__ import annotations

from softgrasp.errors import InfeasibleGrasp, NotConverged, SimulationUnstable, SoftgraspError

__all__ = ["BAD_INPUT", "EXIT_CODES", "INTERNAL", "INTERRUPTED", "NOT_DONE", "OK", "exit_status"]

OK, NOT_DONE, BAD_INPUT, INTERNAL, INTERRUPTED = 0, 1, 2, 3, 130

#: Each exit status and its meaning, for ``softgrasp --help`` and the documentation.
EXIT_CODES = {
    OK: "done",
    NOT_DONE: "no grasp holds the object, execute dropped it, a sweep case failed, or a solver found "
    "no equilibrium or blew up (valid input, no result)",
    BAD_INPUT: "bad input: an option, file, mesh, material or output folder refused, or a missing extra",
    INTERNAL: "internal error (a bug; rerun with --debug for its traceback)",
    INTERRUPTED: "interrupted",
}

#: The errors of a computation that ended without its result on valid input.
_NOT_DONE = (InfeasibleGrasp, NotConverged, SimulationUnstable)


def exit_status(exc: SoftgraspError) -> int:
    """The exit status of a deliberate error: :data:`NOT_DONE` or :data:`BAD_INPUT`."""
    return NOT_DONE if isinstance(exc, _NOT_DONE) else BAD_INPUT
