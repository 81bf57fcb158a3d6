"""A bin reclaimed from the top: last in, first out.

Source: the opposite limit of plug flow (Wambeke et al. 2018's FIFO stockpile
model): a stacker-reclaimer working the face it last stacked takes the newest
material first. The held particles form a stack in arrival order; the
feeder takes the newest first. No parameters (``rng`` is accepted, as every
storage model must, and unused: nothing is drawn).
"""

import numpy as np

from cosim.storage import StorageModel


class LifoStorage(StorageModel):
    """Last in, first out: the base class runs the feeder, this orders the stack."""

    name = "lifo"
    checkpointable = True

    def __init__(self, *, rng=None):
        super().__init__(rng=rng)
        self._stack = np.empty(0, dtype=np.uint64)  # oldest first

    def receive(self, ids, t):
        self._stack = np.concatenate((self._stack, np.asarray(ids, dtype=np.uint64)))

    def held_ids(self):
        return self._stack[::-1]

    def _forget(self, ids):
        self._stack = self._stack[: self._stack.size - ids.size]
