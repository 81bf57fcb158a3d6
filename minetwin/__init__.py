"""The MineTwin application: the ``minetwin`` command line (``cli``, ``commands``),
the pytest plugin for co-simulation tests (``testing``), and the orchestration of
the OPC UA integration test (``harness``). It sits above every other package and
is the only one that may import them all (docs/architecture.md, "Layers")."""
