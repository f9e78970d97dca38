"""The subcommands of ``orbit-tracking`` (:mod:`orbit_tracking.tools.cli`), grouped by
what they work on; each module has one ``add_<command>`` function per subcommand that adds
its parser and handler."""

__all__: list[str] = []
