"""The Responsive Link (Responsive Processor paper, Sec. 2-3) in software: an event link that bulk
data can never delay, next to a data link.  packet.py and fec.py are the wire, routing.py the
routing table, node.py a node's forwarding and overtaking, all sans IO."""
