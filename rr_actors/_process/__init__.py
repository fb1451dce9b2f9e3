"""Manager processes: the child's side, the parent's handle, spares, remote handles."""
