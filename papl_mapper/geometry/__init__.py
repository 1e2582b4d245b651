"""geometry stage of papl-mapper."""
