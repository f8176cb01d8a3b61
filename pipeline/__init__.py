"""The user-facing side of sgdslam: the `replay` command, its Rerun recordings and its output files.

`pipeline.replay_graph.replay_graph` replays a pose-graph file through the optimizer and writes the
optimised graph, a JSON summary and a Rerun recording of every iteration. `pipeline.recording` is the only
module that imports rerun.
"""
