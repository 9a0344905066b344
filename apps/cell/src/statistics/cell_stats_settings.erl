%% @doc The settings object of the statistics, `Settings/statistics.json': the shift
%% plan and how long records are kept. A change applies at once: the current shift is
%% worked out again at the next second.
-module(cell_stats_settings).
-behaviour(cell_settings_schema).

-export([name/0, fields/0, check/1]).

-spec name() -> statistics.
name() -> statistics.

-spec fields() -> [cell_settings_schema:field()].
fields() ->
    [#{name => shifts, type => {list, {string, 5}, 12},
       default => [<<"06:00">>, <<"14:00">>, <<"22:00">>],
       doc => <<"Start time of each shift, local time \"HH:MM\", in ascending order; a "
                "shift ends where the next begins.">>},
     #{name => trace_days, type => {integer, 1, 3650}, default => 90, unit => <<"days">>,
       doc => <<"How long a product's history is kept after it left the cell.">>},
     #{name => trace_max_records, type => {integer, 1000, 10000000}, default => 6000000,
       doc => <<"Most records of product histories kept (about 170 bytes each on disc, "
                "some 40 a product; the file cannot pass 2 GB): past it the histories of "
                "the products that left longest ago are removed first.">>},
     #{name => journal_max_mb, type => {integer, 1, 4096}, default => 128, unit => <<"MB">>,
       doc => <<"Most the trace journal (Databases/cell_trace.journal) may hold of the "
                "records of products' ways the database has not yet taken; while the "
                "database works it is emptied every second, while it cannot be opened it "
                "grows (some 10 kB a product). From 80 % a warning is raised; at the bound "
                "no new record is taken: a task that must record a product's way stops "
                "with an error, as when the disk is full, and nothing recorded is lost.">>},
     #{name => shift_days, type => {integer, 1, 3650}, default => 400, unit => <<"days">>,
       doc => <<"How long the statistics of each shift are kept (the totals are kept "
                "for ever).">>}].

%% @doc The shift plan is a list of "HH:MM" times, ascending.
-spec check(map()) -> ok | {error, cell_settings_schema:path(), term()}.
check(#{shifts := Shifts}) ->
    case cell_stats_shift:parse_all(Shifts) of
        {ok, _} -> ok;
        {error, {I, Why}} -> {error, [shifts, I], Why}
    end.
