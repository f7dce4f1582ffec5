"""Files: the one atomic-write helper (:mod:`.atomic`), EXR buffers and images (:mod:`.exr`),
PNG previews and montages (:mod:`.images`)."""
