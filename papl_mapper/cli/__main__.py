"""`python -m papl_mapper.cli`."""

from papl_mapper.cli import entry

entry()
