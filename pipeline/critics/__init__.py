"""Critics fitted post hoc on a specialist's buffer, and the fidelity of any critics."""
