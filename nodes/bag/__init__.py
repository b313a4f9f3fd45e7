"""Bags: record, replay, inspect, recover and export bus sessions as MCAP files.

Python API, `nodes.bag.reader`: `read_bag(path, topics)` yields (topic, message,
log_time_ns); `BagReader(path)` gives `.topics()`, `.attachments()`, `.metadata()` and
undecoded `.messages()`; `BagError` names the file and what is wrong with it. The nodes
are `bag_record` (`nodes.bag.recorder`) and `bag_play` (`nodes.bag.player`); `fv bag`
is `nodes.bag.commands`; the payload layout is described in `nodes.bag.codec`. (Nothing
is imported here, so `fv --help` does not load mcap.)
"""
