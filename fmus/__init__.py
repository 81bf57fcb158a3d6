"""Sources and build tooling of the crusher and mill FMUs (fmus/README.md)."""
