"""The robot model: spatial algebra, the rigid-body tree and its dynamics, closed chains,
contacts, the model files and facts about them."""
