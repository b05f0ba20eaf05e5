"""A whole run: the decisions the data does not state (``conventions``, ``noise``, ``drift``,
``timing``) and the loop over a stream of steps (``runner`` over ``online.OnlineRun``)."""
