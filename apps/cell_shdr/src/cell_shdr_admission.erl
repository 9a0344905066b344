%% @doc Who may connect to the adapter (pure): at most `max_clients' clients at once.
%% When every place is taken, the oldest client that has not yet shown life (its first
%% `* PING') gives its place to the newcomer, so connections that never PING can never
%% lock an agent out; when every client has shown life, the newcomer is refused. A
%% limit lowered below the clients connected closes none of them: newcomers are
%% admitted again once enough have gone.
-module(cell_shdr_admission).

-export([admit/2]).

-export_type([client/0]).

%% A connected client: when it connected (any increasing number), whether it has
%% shown life, and what names it.
-type client() :: {Since :: integer(), Alive :: boolean(), Id :: term()}.

%% @doc Whether a newcomer may connect beside `Clients', and at whose expense.
-spec admit([client()], pos_integer()) -> admit | {evict, term()} | full.
admit(Clients, Max) when length(Clients) < Max ->
    admit;
admit(Clients, _Max) ->
    case lists:sort([{Since, Id} || {Since, false, Id} <- Clients]) of
        [{_, Id} | _] -> {evict, Id};
        [] -> full
    end.
