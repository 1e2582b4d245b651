"""papl-mapper: offline principal-axis-anchored point-line mapping of recorded walkthroughs."""

import logging

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
