"""Serving calibrate requests: the engine that turns a body into response bytes (`engine`,
with the JSON and nuScenes documents of `documents`), where it runs — a thread, the event loop
or a worker process (`runner`, `parent_watch`) — the profile cache (`cache`), the request's fit
to its profile (`profile_match`), the Arrow route below FastAPI's routing (`arrow_route`), and
a 2-D profile's `images` (`images2d`) and Arrow batch (`arrow2d`)."""
