"""``cae-lcd``: the command line, on top of every package (it imports them; nothing imports it)."""
