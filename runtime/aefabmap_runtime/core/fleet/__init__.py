"""Other robots' places: the wire format robots exchange and the remote places beside the own map."""
