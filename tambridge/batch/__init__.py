"""``tambridge batch``'s library parts: which sequences a batch runs (:mod:`.sequences`) and its summary
(:mod:`.summary`); the Ray driver and tasks are in :mod:`pipelines.batch`."""
