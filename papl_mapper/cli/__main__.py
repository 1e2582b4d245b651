"""`python -m papl_mapper.cli`."""

import sys

from papl_mapper.cli import main

sys.exit(main())
