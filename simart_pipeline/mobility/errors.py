"""Errors of recorded trajectories, shared by the CSV reader (:mod:`.replay`) and the bag reader
(:mod:`.bags`), which both raise them."""


class ReplayError(ValueError):
    """A recorded trajectory that cannot be replayed; the message names the file."""
