"""Everything a user runs that is not a node: the ``orbit-tracking`` command
(:mod:`.cli`, its subcommands in :mod:`.commands`), the offline pipelines per command
(:mod:`.simulate`, :mod:`.triangulate`, :mod:`.estimate`, :mod:`.recording`, with
:mod:`.bag_inputs` and :mod:`.evaluation`), the main job's live pass (:mod:`.live`), the
HTML report (:mod:`.report`) and the benchmark suites (:mod:`.bench`)."""

__all__: list[str] = []
