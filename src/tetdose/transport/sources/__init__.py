"""Sources: the plan's beams flattened to arrays (:mod:`.arrays`) and the kernels that sample a
source particle's energy, position and direction from them (:mod:`._sample`)."""
