"""The ordinary traffic's frames, shared by `cell bench background` and its --xdp sweep."""

HEADERS = 46  # UDP + IPv4 + Ethernet + FCS: frame bytes a datagram's payload does not count
FRAMES = (64, 1280)  # the frame sizes of ordinary traffic (the paper's smallest and MTU-sized)
