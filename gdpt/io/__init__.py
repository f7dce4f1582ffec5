"""Files: the one atomic-write helper (:mod:`.atomic`), EXR buffers and images (:mod:`.exr`),
EXRs of Mitsuba's ``aov`` integrator (:mod:`.mitsuba_aov`),
PNG previews and montages (:mod:`.images`)."""
