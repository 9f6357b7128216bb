"""The service's routes, one router per group: :mod:`.measurements` (``/v1/measurements``),
:mod:`.tracks` (``/v1/tracks``) and :mod:`.service` (``/health``, ``/ready``, ``/metrics``)."""

from .measurements import router as measurements
from .service import router as service
from .tracks import router as tracks

__all__ = ["ROUTERS"]

#: in the order of the API description
ROUTERS = (measurements, tracks, service)
