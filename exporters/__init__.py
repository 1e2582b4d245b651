"""Exporters: one module per file format, registered by suffix; import as papl_mapper.exporters."""
