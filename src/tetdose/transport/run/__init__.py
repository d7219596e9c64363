"""Running a transport: settings (:mod:`.settings`), the job (arrays for the kernels,
:mod:`.job`), the numba batch loop (:mod:`._batches`) and its distribution on dask
(:mod:`.distributed`) with bitwise the same result."""
