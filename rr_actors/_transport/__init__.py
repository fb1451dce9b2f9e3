"""How registrar messages cross processes: the carrier interface and its implementations."""

from rr_actors._transport.unix import AttachedSystem, RemotePeer, System, SystemAddress, attach

__all__ = ["AttachedSystem", "RemotePeer", "System", "SystemAddress", "attach"]
