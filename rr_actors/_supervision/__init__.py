"""Supervision trees after Erlang/OTP's `supervisor`: policy on top of the process layer."""

from rr_actors._supervision.supervisor import ChildCounts, ChildInfo, Supervisor

__all__ = ["ChildCounts", "ChildInfo", "Supervisor"]
