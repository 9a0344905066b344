%% A unit whose declaration is its `decl' argument: for tests of the checks at the door.
-module(cell_test_decl_unit).
-behaviour(cell_unit).

-export([unit/1]).

unit(#{decl := Decl}) -> Decl.
