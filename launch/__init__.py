"""What a person runs: the `sygrid` command, the demo, and the configuration files of cells and datasets."""
