"""Host side of the board link: the board interface, transports and the wire codec."""
