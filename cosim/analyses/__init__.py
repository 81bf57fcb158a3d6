"""The paper's analyses on tracked particles (section "Results").

One module per analysis, each a library of functions that take a run's
time series (pandas) and event store (``cosim.events.EventStore``), so they
apply to any run, not only the simulator's:

``mwd``             hardness from measurement-while-drilling via the crusher torque
``feed_prediction`` mill-feed properties predicted from the storage model
``grindability``    Bond work index in the mill and its backtracking to ore blocks
``sensitivity``     how the above degrade with errors in the recorded origins
``tracking``        residence intervals and occupancy sums shared by all of them
``profile_run``     the quadratic-hardness simulator run the reproductions analyse

Each analysis module also exposes ``DESCRIPTION`` and ``reproduce(out_dir, *,
quick, progress)`` for ``minetwin reproduce NAME`` (minetwin/commands/reproduce.py).
"""
