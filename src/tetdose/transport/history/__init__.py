"""The history loop and its scoring: one source particle and its secondaries followed to the end
through the world (:mod:`._photon`), the energy ledger, and the :class:`~.result.DoseResult`
built from the tallies."""
