"""NGPT training: :mod:`.dataset` (render crops, manifest, crop reader) -> :mod:`.train` (the
loop over :mod:`.config` (run settings, resume rule), :mod:`.schedule` (learning rate),
:mod:`.augment` (augmentations), :mod:`.batches` (held-out split, samples, batches),
:mod:`.step` (loss, optimizer update), :mod:`.validation` and :mod:`.run_dir` (run directory))
-> :mod:`.checkpoint` (atomic checkpoints) -> :mod:`.model_report` (held-out comparison,
shipping into ``gdpt/models``); :mod:`.finetune` fine-tunes OIDN's U-Net with the same
pieces."""
