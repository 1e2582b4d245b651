"""Off-screen previews, the HTML report and the desktop viewer; import as papl_mapper.gui."""
