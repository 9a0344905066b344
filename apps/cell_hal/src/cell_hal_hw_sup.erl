%% @doc Supervises the hardware objects, one child per object id.
-module(cell_hal_hw_sup).
-behaviour(supervisor).

-export([start_link/0, start_object/4, stop_object/1]).
-export([init/1]).

-spec start_link() -> {ok, pid()} | ignore | {error, term()}.
start_link() ->
    supervisor:start_link({local, ?MODULE}, ?MODULE, []).

%% @doc Starts a hardware object.
-spec start_object(atom(), cell_hal_hw:kind(), module(), map()) ->
          ok | {error, {already_exists, atom()} | term()}.
start_object(Id, Kind, Mod, Opts) ->
    Spec = #{id => Id, start => {cell_hal_hw, start_link, [Id, Kind, Mod, Opts]}},
    case supervisor:start_child(?MODULE, Spec) of
        {ok, _} -> ok;
        {error, {already_started, _}} -> {error, {already_exists, Id}};
        {error, already_present} -> {error, {already_exists, Id}};
        %% The implementation's refusal, without the child spec the supervisor adds.
        {error, {Why, Child}} when element(1, Child) =:= child -> {error, Why};
        {error, _} = Error -> Error
    end.

%% @doc Stops a hardware object.
-spec stop_object(atom()) -> ok | {error, not_present}.
stop_object(Id) ->
    case supervisor:terminate_child(?MODULE, Id) of
        ok -> ok = supervisor:delete_child(?MODULE, Id);
        {error, not_found} -> {error, not_present}
    end.

-spec init([]) -> {ok, {supervisor:sup_flags(), [supervisor:child_spec()]}}.
init([]) ->
    %% A device that misbehaves makes its object report `down', not crash; a crash is a
    %% bug in an implementation. A few a minute are tolerated, then the HAL escalates.
    {ok, {#{strategy => one_for_one, intensity => 5, period => 60}, []}}.
