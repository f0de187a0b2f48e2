"""Sub-commands of the ``hostlink`` console script (see ``hostlink.cli``)."""
