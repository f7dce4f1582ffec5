"""NGPT training: :mod:`.dataset` (render crops, manifest, crop reader) -> :mod:`.train`
(augmentations, run directory, loop) -> :mod:`.checkpoint` (atomic checkpoints) ->
:mod:`.model_report` (held-out comparison, shipping into ``gdpt/models``)."""
