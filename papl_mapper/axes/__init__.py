"""axes stage of papl-mapper."""
