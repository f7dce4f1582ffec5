"""Training the reconstruction networks of every family (:mod:`gdpt.reconstruct.families`).

:mod:`.preprocess` (render crops; their files: :mod:`.manifest`) -> :mod:`.dataset` (read
them) -> :mod:`.train` (``gdpt train``: the family of the design, its plan, the loop) ->
:mod:`.loop` (the one training loop: run directory (:mod:`.run_dir`), settings
(:mod:`.config`), schedule (:mod:`.schedule`), optimizer update (:mod:`.step`), checkpoints
(:mod:`.checkpoint`), exact resume, ``torchrun``) running a family's plan, named after its
family: :mod:`.dense_unet` (NGPT's dense U-Net), :mod:`.oidn_finetune` (OIDN's U-Net fine-tuned),
:mod:`.combiner` (the combiner), :mod:`.kpcn` (KPCN), built from :mod:`.augment`,
:mod:`.batches` and :mod:`.validation` -> :mod:`.model_report` (held-out comparison, shipping
into ``gdpt/models``) and :mod:`.refinement` (choosing a fine-tuned network's gated refinement).
"""
