"""Running the agent on the host: training, pre-training, evaluation, experiments,
checkpoints, metrics, plots, videos and inspection."""
