"""swarmsplat's top layer: Gaussian maps, tracking, mapping, agents and teams, robot nodes, datasets, metrics, CLI."""
