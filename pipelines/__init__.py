"""Pipelines: short recipes chaining the stages; import as papl_mapper.pipelines."""
