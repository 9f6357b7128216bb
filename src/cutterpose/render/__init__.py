"""Synthetic images with known poses: :mod:`.analytic` (closed-form ray casting of the holder,
fast, the paper's lab) and, with the ``[field]`` extra, :mod:`.pbr` (Mitsuba 3 path tracing of
worn holders in field conditions)."""
