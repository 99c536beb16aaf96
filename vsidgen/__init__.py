"""vsidgen: aircraft system identification from YAML model specs."""

__version__ = "0.1.0"

from .errors import DataError, SpecError, SpecWarning, VsidgenError  # noqa: E402
from .model import Model  # noqa: E402

__all__ = ["DataError", "Model", "SpecError", "SpecWarning", "VsidgenError", "__version__"]
