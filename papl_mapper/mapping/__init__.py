"""mapping stage of papl-mapper."""
