"""HTTP layer of the gateway: request/response models, routes, middleware."""
