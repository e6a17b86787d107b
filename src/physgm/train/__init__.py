"""Training stages: LightningModules (losses, optimisers, logging), callbacks and the run entry."""
