"""Pure maths and the data it works on: the Beta policy, returns and baselines, the observation
normaliser, the REINFORCE update, the merge of branches, and the agent file that holds them.
No processes, no environments, no pool files (an agent's own bytes aside)."""
