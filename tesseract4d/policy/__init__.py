"""The closed-loop policy: inverse dynamics over predicted 4D scenes, the policy loop, rollout evaluation."""
