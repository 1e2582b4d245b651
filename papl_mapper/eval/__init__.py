"""eval stage of papl-mapper."""
