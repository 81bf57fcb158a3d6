"""Sources and build tooling of the crusher and mill FMUs (DESIGN.md section 5)."""
