"""Presets: YAML files of the one config tree (slam.config.SlamConfig), loaded by name with
`SlamConfig.preset(NAME)` or `--preset NAME`. docs/config.md describes every section and key."""
