"""Input and output: sequence folders, atomic writes, file formats."""
