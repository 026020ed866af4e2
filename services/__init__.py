"""The cell's services, one module per service (installed as cell.services).

Each module is a thin adapter: it defines SERVICE, a cell.service.ServiceSpec
whose run(ctx) wires an engine from the service's subsystem package (cell.robot,
cell.dataplane, cell.controller, ...) to the bus.  cell.service.BUILTIN lists
them; users add their own with [services.plugins] in the config.
"""
