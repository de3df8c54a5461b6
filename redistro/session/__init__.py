"""The session: its pieces, composed by ``redistro session`` (:mod:`.run`) and
``redistro node`` (:mod:`.node`): pre-flight checks, progress, the summary."""
