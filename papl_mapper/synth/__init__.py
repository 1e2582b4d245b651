"""synth stage of papl-mapper."""
