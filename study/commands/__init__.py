"""The console's commands, by what they work on (:mod:`study.cli` builds the app of them)."""
