"""Quickstart: one provider registrar, one consumer registrar, load / status / unload."""

import threading

import rr_actors as rr

heard = threading.Event()

erm = rr.ResourceRegistrar.start("quickstart-erm")  # the provider (a resource manager)
app = rr.ResourceRegistrar.start("quickstart-app")  # the consumer (an application)
try:
    erm.register_server(
        "greeter",
        load=lambda request: f"hello, {request['name']}",  # runs once per distinct request
        unload=lambda request, response: print(f"unloaded {response!r}"),
    )

    def on_status(query: rr.Query, update: rr.StatusUpdate) -> None:
        print(f"{query.id[:8]} heard {update.status.name}: {update.message}")
        heard.set()

    first = app.call("quickstart-erm", "greeter", {"name": "world"}, on_status=on_status)
    second = app.call("quickstart-erm", "greeter", {"name": "world"})  # equal request: shared
    print(f"response: {first.response!r}; shared: {first.response == second.response}")

    erm.send_status(second.id, rr.Status.WARNING, "battery low")  # reaches every consumer
    if not heard.wait(5):
        raise SystemExit("the status never arrived")

    app.unload(first.id)  # one consumer left: nothing is unloaded yet
    app.unload(second.id)  # last consumer released: the server's unload runs
finally:
    app.stop()
    erm.stop()
