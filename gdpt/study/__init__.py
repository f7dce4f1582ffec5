"""The equal-time study: every method at measured equal time against a path-traced reference.

:mod:`.config` (profiles) -> :mod:`.scenes` (which scenes, loaded through
:mod:`gdpt.scenes.loading`) -> :mod:`.references` -> :mod:`.methods` (registry of timed
methods) -> :mod:`.calibration` (spp per budget) -> :mod:`.evaluate` (the harness) ->
:mod:`.results` (``results.json`` schema) -> :mod:`.report` (markdown, HTML, plots);
:mod:`.demo` runs it on the built-in Cornell box.
"""
