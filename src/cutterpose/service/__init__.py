"""The measurement service, ``cutterpose serve`` (issue 12): a FastAPI application
(:mod:`.app`, its routes in :mod:`.routes` by group, the shared state as dependencies in
:mod:`.deps`) under uvicorn with limits on slow and hostile clients (:mod:`.server`), over a
pool of worker processes (:mod:`.workers`) that run :func:`cutterpose.pipeline.measure`
(:mod:`.jobs`), a SQLite record (:mod:`.store`), the cell file (:mod:`.config`) and Prometheus
metrics (:mod:`.metrics`). The client is :mod:`cutterpose.client`; the API is described in
``docs/service.md``.

Nothing in the core imports this package (``tests/test_layout.py``).
"""
