"""The A2CAT-VN agent: its network, losses, replay buffer and jitted update."""
