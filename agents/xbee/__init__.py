"""XBee API-mode gateway: API frame codec, simulated 802.15.4 air, gateway and ``xbee://`` link."""
