"""Query gateway: natural-language and example queries over HTTP, trajectory and map export, a web viewer."""
