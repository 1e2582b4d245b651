"""backend stage of papl-mapper."""
