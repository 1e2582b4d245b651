"""frontend stage of papl-mapper."""
