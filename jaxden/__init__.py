"""jaxden: Monte Carlo denoising research in JAX.

Progressive denoising (Firmino et al. 2022), weight-sharing kernel prediction (Fan et al. 2021),
Stein's unbiased risk estimate with jvp divergence, and a Mitsuba 3 data generator.
"""

__version__ = "0.1.0"

from jaxden.errors import JaxdenError  # noqa: E402
from jaxden.frame import Frame  # noqa: E402

__all__ = ["Frame", "JaxdenError", "__version__"]
