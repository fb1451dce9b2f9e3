"""rr_actors_lab: the tools beside the runtime (issue 54, "the runtime reads alone").

The experiments and their checker (`rr_actors_lab.experiments`), the thesis's robot mission
(`rr_actors_lab.mission`), the observer's page (`rr_actors_lab.observe`), the classroom kit
(`rr_actors_lab.teach`), the OpenTelemetry spans built from the event stream
(`rr_actors_lab.otel`) and the `rr-actors` command line. They import the runtime
(`rr_actors`); the runtime never imports them (an import-linter contract). The same
distribution installs both; each tool's extra (`rr_actors[experiments]`, `[observe]`,
`[demo]`, `[teach]`, `[otel]`) brings what it needs.

Their former names (`rr_actors.experiments`, `rr_actors.observe`, ...) still import: they
are the same modules.
"""
