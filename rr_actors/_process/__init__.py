"""Manager processes: the child's side, the parent's handle, the control pipe's messages
(`control`), spares, remote handles."""
